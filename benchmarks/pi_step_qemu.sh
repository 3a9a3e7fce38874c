#!/usr/bin/env bash
# Count the instructions of one control step (benchmarks/pi_step.py) as a Raspberry Pi OS 64-bit
# robot runs it, and turn them into time on a Pi 3B's Cortex-A53 (docs/robot-agent.md).
#
#   sudo benchmarks/pi_step_qemu.sh [WORK_DIR]      (default /var/tmp/pi-step-qemu)
#
# What runs: Debian 12's arm64 python3.11 (the Python of Raspberry Pi OS bookworm), with numpy,
# msgspec and pyyaml from PyPI's aarch64 wheels (what pip installs into the robot's venv; the same
# versions as the calling Python's), and no numba, as deploy/install-pi.sh installs it; run by
# qemu-aarch64 with `-cpu cortex-a53` (the A53's instruction set: numpy picks the code paths the Pi
# would) and a TCG plugin counting the guest instructions (benchmarks/qemu_insn_count.c).
# Each part runs twice, for STEPS_SHORT and STEPS_LONG steps; the difference of the two counts over
# the difference of the steps is the instructions of one step, without the start-up.
#
# The arm64 root is debootstrap's first stage (--foreign) with every downloaded package unpacked:
# nothing of it is ever executed natively and no binfmt_misc handler is needed, because qemu runs
# the root's python with -L. Root is needed for debootstrap and apt-get only; everything lives in
# WORK_DIR (a few hundred MB), outside the checkout.
#
# Time per step = instructions / (IPC x clock). The Pi 3B's A53 runs at 1.2 GHz, and at 600 MHz
# when throttled (under-voltage, heat) or while the ondemand governor sees it mostly idle, as a
# 10 Hz loop leaves it. IPC is not measured here (emulation has no timing): printed for 0.25, 0.5
# and 1.0, see docs/robot-agent.md.
set -euo pipefail

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
work=${1:-/var/tmp/pi-step-qemu}
python=${PYTHON:-python3}
steps_short=${STEPS_SHORT:-100}
steps_long=${STEPS_LONG:-1100}
mkdir -p "$work"

need=()
command -v qemu-aarch64 >/dev/null || need+=(qemu-user)
command -v debootstrap >/dev/null || need+=(debootstrap)
command -v gcc >/dev/null || need+=(gcc)
if [ ${#need[@]} -gt 0 ]; then
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null
fi

root=$work/root
if [ ! -x "$root/usr/bin/python3.11" ]; then
  echo "# debootstrap: Debian 12 arm64 minbase with python3 into $root" >&2
  rm -rf "$root"
  debootstrap --arch=arm64 --foreign --variant=minbase --include=python3 bookworm "$root" \
    http://deb.debian.org/debian >"$work/debootstrap.log" 2>&1 \
    || { tail -20 "$work/debootstrap.log" >&2; exit 1; }
  for deb in "$root"/var/cache/apt/archives/*.deb; do
    dpkg-deb -x "$deb" "$root"
  done
fi

site=$work/site-arm64
if [ ! -d "$site/numpy" ]; then
  echo "# PyPI's aarch64 wheels into $site" >&2
  versions=$("$python" -c 'import msgspec, numpy, yaml
print(f"numpy=={numpy.__version__} msgspec=={msgspec.__version__} pyyaml=={yaml.__version__}")')
  # shellcheck disable=SC2086  # the versions are three words
  "$python" -m pip download -q --only-binary=:all: --implementation cp --python-version 3.11 \
    --platform manylinux_2_28_aarch64 --platform manylinux_2_17_aarch64 \
    --platform manylinux2014_aarch64 -d "$work/wheels" $versions
  mkdir -p "$site"
  for wheel in "$work"/wheels/*.whl; do
    "$python" -m zipfile -e "$wheel" "$site"
  done
fi

plugin=$work/libinsncount.so
gcc -O2 -Wall -shared -fPIC -o "$plugin" "$repo/benchmarks/qemu_insn_count.c"

count() {  # count PART STEPS: the guest instructions of the whole process
  PYTHONPATH=$repo:$site PYTHONHASHSEED=0 PYTHONDONTWRITEBYTECODE=1 OPENBLAS_NUM_THREADS=1 \
    qemu-aarch64 -cpu cortex-a53 -plugin "$plugin" -L "$root" "$root/usr/bin/python3.11" \
    "$repo/benchmarks/pi_step.py" --only "$1" --steps "$2" 2>&1 >/dev/null \
    | sed -n 's/^guest_instructions: //p'
}

echo "# arm64 python $(PYTHONPATH=$site qemu-aarch64 -cpu cortex-a53 -L "$root" \
  "$root/usr/bin/python3.11" -c 'import sys, numpy; print(sys.version.split()[0], "numpy", numpy.__version__)'),\
 no numba; steps $steps_short and $steps_long"
for part in basic_kernels basic_loop object_kernels object_loop; do
  short=$(count "$part" "$steps_short")
  long=$(count "$part" "$steps_long")
  if [ -z "$short" ] || [ -z "$long" ]; then
    echo "pi_step_qemu.sh: no count for $part (run the qemu command by hand to see why)" >&2
    exit 1
  fi
  "$python" - "$part" "$short" "$long" "$steps_short" "$steps_long" <<'EOF'
import sys

part, short, long, n_short, n_long = sys.argv[1], *map(int, sys.argv[2:])
per_step = (long - short) / (n_long - n_short)
print(f"{part}_instructions: {per_step:.0f} instructions")
for ghz in (1.2, 0.6):
    for ipc in (1.0, 0.5, 0.25):
        ms = per_step / (ipc * ghz * 1e9) * 1e3
        print(f"{part}_at_{ghz}GHz_ipc_{ipc}: {ms:.2f} ms")
EOF
done
