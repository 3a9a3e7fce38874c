#!/usr/bin/env bash
# Install the robot agent on a Raspberry Pi OS 64-bit (Debian bookworm) robot.
#
#   sudo deploy/install-pi.sh ROBOT_ID [SECRET_FILE]
#
# Run from a checkout of this repository on the Pi. Idempotent: running it again upgrades the
# software and keeps an existing /etc/minimize-surprise/agent.yaml and secret.
set -euo pipefail

robot_id=${1:?usage: install-pi.sh ROBOT_ID [SECRET_FILE]}
secret_src=${2:-}
repo=$(cd "$(dirname "$0")/.." && pwd)
prefix=/opt/minimize-surprise
etc=/etc/minimize-surprise

if [ "$(id -u)" -ne 0 ]; then
  echo "install-pi.sh: run as root (sudo)" >&2
  exit 1
fi

echo "== Debian packages"
apt-get update -qq
# aseba: asebamedulla; i2c-tools: i2cdetect to check the light and force sensors' wiring.
# locales: medulla reports an Aseba compile error only if the en_US.UTF-8 locale is installed;
# without it, it aborts instead (whatever locale it runs under). Our programs compile, so this
# only matters when someone edits them, but then the reason is worth having.
apt-get install -y -qq aseba i2c-tools python3-venv dbus locales
if ! locale -a | grep -qi '^en_US.utf-\?8$'; then
  sed -i 's/^# *en_US.UTF-8 UTF-8/en_US.UTF-8 UTF-8/' /etc/locale.gen
  locale-gen
fi
# Enable the I2C bus (no-op if raspi-config is absent or it is already on).
command -v raspi-config >/dev/null && raspi-config nonint do_i2c 0 || true

echo "== user 'surprise' with the dialout (Thymio USB serial) and i2c groups"
getent group i2c >/dev/null || groupadd --system i2c
id surprise >/dev/null 2>&1 || useradd --system --home-dir "$prefix" --shell /usr/sbin/nologin surprise
usermod -aG dialout,i2c surprise

echo "== virtual environment in $prefix/venv"
python3 -m venv "$prefix/venv"
"$prefix/venv/bin/pip" install -q --upgrade pip
"$prefix/venv/bin/pip" install -q "$repo[robot]"

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
