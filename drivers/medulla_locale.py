"""The locale asebamedulla needs, and whether this machine has it (docs/thymio.md, "The locale").

Debian's ``asebamedulla`` builds a C++ ``std::locale("en_US.UTF-8")`` whenever it loads an Aseba
program, any program, our failsafe and empty ones included. Where that locale has not been
generated, the constructor throws ``std::runtime_error`` ("locale::facet::_S_create_c_locale
name not valid"), nothing catches it, and medulla aborts without answering the ``LoadScripts``
call: the caller sees only that medulla left the bus. :func:`locale_installed` lets the driver
tell that cause from the others and name the command that fixes it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

__all__ = ["LOCALE_FIX", "MEDULLA_LOCALE", "abort_reason", "locale_installed"]

#: The locale medulla constructs to load a program.
MEDULLA_LOCALE = "en_US.UTF-8"
#: One command that generates it on Debian and Raspberry Pi OS (deploy/install-pi.sh does this).
LOCALE_FIX = (
    "sudo apt-get install -y locales && echo 'en_US.UTF-8 UTF-8' | sudo tee -a /etc/locale.gen "
    "&& sudo locale-gen"
)
#: glibc's LC_ALL_MASK: every category bit (0..12) except LC_ALL's own (6), as libstdc++ asks.
_LC_ALL_MASK = ((1 << 13) - 1) & ~(1 << 6)


def locale_installed(name: str = MEDULLA_LOCALE) -> bool | None:
    """Whether the C library here can load the locale ``name``; None where that cannot be told
    (no glibc). Asks the way medulla's C++ library does (``newlocale``), so ``LOCPATH`` and the
    locale archive count as they do for medulla on the same machine; it changes no locale."""
    libc = _libc()
    if libc is None:
        return None
    handle = libc.newlocale(_LC_ALL_MASK, name.encode(), None)
    if not handle:
        return False
    libc.freelocale(handle)
    return True


@functools.cache
def _libc() -> ctypes.CDLL | None:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.newlocale.restype = ctypes.c_void_p
        libc.newlocale.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_void_p]
        libc.freelocale.argtypes = [ctypes.c_void_p]
    except (OSError, AttributeError):
        return None
    return libc


def abort_reason(what: str, path: str) -> str:
    """One line on a medulla that left the bus instead of answering ``LoadScripts``."""
    if locale_installed() is False:
        return (
            f"Thymio: asebamedulla aborts loading any program, {what} included: the "
            f"{MEDULLA_LOCALE} locale it needs is not installed; run: {LOCALE_FIX}"
        )
    return (
        f"Thymio: asebamedulla ended while loading {what} {path} (it aborts on a malformed "
        "program file; its own output, e.g. journalctl -u asebamedulla, says why)"
    )
