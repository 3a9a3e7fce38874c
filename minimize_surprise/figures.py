"""Writing a drawn figure to files: every picture of the project goes through :func:`save_figure`.

The figure is rendered into memory first, in every format asked for, and only then is each file
written with :func:`minimize_surprise.files.write_atomic`: a figure that fails to draw writes
nothing, and a reader (a report's page, a file browser) sees the old picture or the new one,
never a half-written one.

This module draws nothing and imports no plotting library: it takes any object with the methods
of matplotlib's ``Figure`` it uses (the packages drawing figures import matplotlib
themselves, only when they draw), so the core package stays free of it.
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, Final, Protocol

from minimize_surprise.files import write_atomic

__all__ = ["DPI", "DURABLE", "FORMATS", "PAD", "TIGHT", "save_figure"]

#: The formats a picture is written in: a raster to look at, a vector one to print.
FORMATS: Final = ("png", "pdf")
#: Resolution of the rasters, in dots per inch: sharp on a slide, small enough to mail.
DPI: Final = 150
#: Crop the picture to what is drawn: titles, labels and legends outside the axes stay in, the
#: empty margin goes (the pixel size then follows the drawing, not the figure's size).
TIGHT: Final = True
#: The margin around a cropped picture, in inches (matplotlib's default).
PAD: Final = 0.1
#: No fsync: a picture is drawn again from the data by the next report, and syncing would cost a
#: disk flush per file. The write is still atomic.
DURABLE: Final = False


class Drawable(Protocol):
    """What :func:`save_figure` needs of a figure: these methods of matplotlib's ``Figure``."""

    dpi: float
    axes: Any

    def savefig(self, fname: Any, **kwargs: Any) -> Any: ...

    def set_dpi(self, val: float) -> None: ...

    def draw_without_rendering(self) -> None: ...

    def get_tightbbox(self) -> Any: ...

    def get_layout_engine(self) -> Any: ...

    def set_layout_engine(self, layout: Any = None) -> None: ...


def save_figure(
    fig: Drawable,
    path: str | Path,
    *,
    formats: Sequence[str] = FORMATS,
    dpi: float | None = DPI,
    tight: bool = TIGHT,
    suffix: bool = True,
    write: Callable[..., None] = write_atomic,
) -> list[Path]:
    """Write ``fig`` in each of ``formats``; the paths written, in the order of ``formats``.

    ``path`` names the files without their extension: ``plots/fitness`` becomes
    ``plots/fitness.png`` and ``plots/fitness.pdf``. ``suffix=False`` writes exactly ``path``
    instead, in the one format given (for a caller handed a whole file name).

    ``dpi`` is the rasters' resolution; None leaves it to matplotlib (its ``savefig.dpi``
    setting, by default the figure's own). ``tight`` crops to what is drawn (``bbox_inches=
    "tight"``); False keeps the figure's size, e.g. for a figure laid out by constrained layout.

    Every format is rendered into memory before any file is written: when drawing fails, no file
    is touched. ``write(path, data, durable=...)`` writes each file's bytes; by default
    :func:`~minimize_surprise.files.write_atomic`, whose OSError propagates as it is. A caller
    that names a failed file in a :class:`~minimize_surprise.errors.FileWriteError` passes its
    own (e.g. ``master_service.rundir.write_atomic``).
    """
    path = Path(path)
    formats = tuple(formats)
    if not formats:
        raise ValueError("save_figure: no format given")
    if not suffix and len(formats) != 1:
        raise ValueError(f"save_figure: suffix=False writes one file, not {len(formats)} formats")
    options: dict[str, Any] = {}
    if dpi is not None:
        options["dpi"] = dpi
    if tight:
        # Several formats share one box; matplotlib finds it by drawing the figure once more.
        # (Without a dpi the box is left to savefig: its resolution is matplotlib's setting.)
        if len(formats) > 1 and dpi is not None:
            options["bbox_inches"] = _tight_box(fig, dpi)
        else:
            options["bbox_inches"] = "tight"
        options["pad_inches"] = PAD
    engine = fig.get_layout_engine()
    once = False
    if engine is not None and not tight and len(formats) > 1 and dpi is not None:
        once = _lay_out(fig, engine, dpi)
    rendered = []
    try:
        for fmt in formats:
            buffer = io.BytesIO()
            fig.savefig(buffer, format=fmt, **options)
            target = path.with_name(f"{path.name}.{fmt}") if suffix else path
            rendered.append((target, buffer.getvalue()))
    finally:
        if once:
            fig.set_layout_engine(engine)
    for target, data in rendered:
        write(target, data, durable=DURABLE)
    return [target for target, _ in rendered]


def _lay_out(fig: Drawable, engine: Any, dpi: float) -> bool:
    # The figure laid out by its engine (constrained layout) once for every format, at the
    # rasters' resolution (the raster is the same to the byte; in the run pictures a PDF's own
    # layout places the axes within 0.005 inch of it), and the engine set aside until the files
    # are rendered: with an engine, savefig lays the figure out and draws it twice per format
    # (once to lay it out, once to render), which is a fifth of the run pictures' time. Whether
    # the engine is set aside; where not, savefig lays the figure out as it always does.
    if not fig.axes:
        return False  # nothing to lay out (matplotlib's draw skips the engine then)
    try:
        with _at_dpi(fig, dpi):
            engine.execute(fig)
    except ValueError:
        return False  # a layout the engine cannot make: matplotlib's draw ignores it, as here
    # No engine at all (matplotlib's "none" keeps a placeholder, for which savefig still draws
    # twice). Where matplotlib's settings put an engine in its place (autolayout), or refuse
    # the change (a colorbar made for the other kind of engine), the figure keeps its own.
    try:
        fig.set_layout_engine(None)
    except RuntimeError:
        return False
    if fig.get_layout_engine() is not None:
        fig.set_layout_engine(engine)
        return False
    return True


def _tight_box(fig: Drawable, dpi: float) -> Any:
    # The box savefig(bbox_inches="tight") crops to, found once for every format: savefig finds
    # it for each by drawing the whole figure once more (a third of a picture's time). Found as
    # savefig finds it, at the rasters' resolution, so the raster is the same to the byte.
    with _at_dpi(fig, dpi):
        fig.draw_without_rendering()
        box = fig.get_tightbbox()
    return box.padded(PAD)


@contextlib.contextmanager
def _at_dpi(fig: Drawable, dpi: float) -> Iterator[None]:
    # The figure at the rasters' resolution for a while (as savefig sets it while it draws).
    saved = fig.dpi
    fig.set_dpi(dpi)
    try:
        yield
    finally:
        fig.set_dpi(saved)
