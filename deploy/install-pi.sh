#!/usr/bin/env bash
# Install the robot agent on a Raspberry Pi OS 64-bit (Debian bookworm) robot.
#
#   sudo deploy/install-pi.sh ROBOT_ID [SECRET_FILE]
#
# Run from a checkout of this repository on the Pi. Idempotent: running it again upgrades the
# software and keeps an existing /etc/minimize-surprise/agent.yaml and secret.
#
# Sourcing the script defines its functions without running it (tests/deploy does).
set -euo pipefail

prefix=/opt/minimize-surprise
etc=/etc/minimize-surprise
# The copy pip builds from; removed when the script exits, however it exits.
build_dir=

# Copy the source tree $1 into the existing directory $2, without the version history, virtual
# environments and what builds and runs leave behind.
copy_source() {
  tar -C "$1" -cf - \
    --exclude=./.git --exclude=./.venv --exclude=./build --exclude=./dist --exclude=./runs \
    --exclude='*.egg-info' --exclude=__pycache__ --exclude=.pytest_cache \
    --exclude=.ruff_cache --exclude=.hypothesis \
    . | tar -C "$2" -xf - --no-same-owner
}

# The commit checked out in $1 ("-dirty" with uncommitted changes to tracked files), or nothing
# when $1 is no git checkout. safe.directory: as root, git refuses the pi user's checkout.
checkout_commit() {
  local commit
  commit=$(git -c safe.directory="$1" -C "$1" rev-parse --verify HEAD 2>/dev/null) || return 0
  if ! git -c safe.directory="$1" -C "$1" diff --quiet HEAD -- 2>/dev/null; then
    commit="$commit-dirty"
  fi
  echo "$commit"
}

# Install the package from the checkout $2, with the robot extra, into the virtual environment
# $1. pip builds inside the tree it is given (build/, *.egg-info): given the checkout, as root,
# it would leave root-owned files in the pi user's tree, and the next `git pull` or install there
# would fail. So it builds from a throw-away copy, which has no .git: the checkout's commit goes
# to the build through MINIMIZE_SURPRISE_COMMIT (setup.py bakes it in; docs/fleet.md).
install_package() {
  local commit
  commit=$(checkout_commit "$2")
  build_dir=$(mktemp -d)
  trap 'rm -rf -- "$build_dir"' EXIT
  copy_source "$2" "$build_dir"
  "$1/bin/pip" install -q --upgrade pip
  MINIMIZE_SURPRISE_COMMIT="$commit" "$1/bin/pip" install -q "${build_dir}[robot]"
}

# Generate the en_US.UTF-8 locale. Debian's asebamedulla needs it: without it, medulla aborts
# (std::runtime_error "locale::facet::_S_create_c_locale name not valid") as soon as it loads any
# program, the failsafe included, whatever locale medulla itself runs under. No robot drives
# without it.
generate_locale() {
  if locale -a | grep -qi '^en_US.utf-\?8$'; then
    return
  fi
  sed -i 's/^# *en_US.UTF-8 UTF-8/en_US.UTF-8 UTF-8/' /etc/locale.gen
  grep -q '^en_US.UTF-8 UTF-8' /etc/locale.gen || echo 'en_US.UTF-8 UTF-8' >> /etc/locale.gen
  locale-gen
}

main() {
  local robot_id=${1:?usage: install-pi.sh ROBOT_ID [SECRET_FILE]}
  local secret_src=${2:-}
  local repo
  repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)

  if [ "$(id -u)" -ne 0 ]; then
    echo "install-pi.sh: run as root (sudo)" >&2
    exit 1
  fi

  echo "== Debian packages"
  apt-get update -qq
  # aseba: asebamedulla; i2c-tools: i2cdetect to check the light and force sensors' wiring;
  # locales: the en_US.UTF-8 locale medulla cannot load a program without (generate_locale).
  apt-get install -y -qq aseba i2c-tools python3-venv dbus locales
  generate_locale
  # Enable the I2C bus (no-op if raspi-config is absent or it is already on).
  if command -v raspi-config >/dev/null; then
    raspi-config nonint do_i2c 0 || true
  fi

  echo "== user 'surprise' with the dialout (Thymio USB serial) and i2c groups"
  getent group i2c >/dev/null || groupadd --system i2c
  id surprise >/dev/null 2>&1 ||
    useradd --system --home-dir "$prefix" --shell /usr/sbin/nologin surprise
  usermod -aG dialout,i2c surprise

  echo "== virtual environment in $prefix/venv"
  python3 -m venv "$prefix/venv"
  install_package "$prefix/venv" "$repo"

  echo "== configuration in $etc"
  install -d -m 0750 -o root -g surprise "$etc"
  if [ ! -f "$etc/agent.yaml" ]; then
    sed "s/^robot_id: .*/robot_id: $robot_id/" "$repo/deploy/examples/agent-thymio-1.yaml" \
      > "$etc/agent.yaml"
    echo "   wrote $etc/agent.yaml: set master.host to the laptop's address"
  fi
  if [ -n "$secret_src" ]; then
    install -m 0640 -o root -g surprise "$secret_src" "$etc/secret.key"
  elif [ ! -f "$etc/secret.key" ]; then
    echo "   no secret yet: copy the master's secret.key to $etc/secret.key (mode 0640, group surprise)"
  fi

  echo "== D-Bus policy and systemd units"
  install -m 0644 "$repo/deploy/dbus/ch.epfl.mobots.Aseba.conf" /etc/dbus-1/system.d/
  systemctl reload dbus || true
  install -m 0644 "$repo/deploy/systemd/asebamedulla.service" /etc/systemd/system/
  install -m 0644 "$repo/deploy/systemd/surprise-agent.service" /etc/systemd/system/
  systemctl daemon-reload
  systemctl enable asebamedulla.service surprise-agent.service
  systemctl restart asebamedulla.service surprise-agent.service

  echo "== done: follow the agent with  journalctl -fu surprise-agent"
}

if [ "${BASH_SOURCE[0]}" = "$0" ]; then
  main "$@"
fi
