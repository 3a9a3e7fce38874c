# Shared by .ci/fresh-root and .ci/pi-root (sourced, not run): a cached clean Debian 12 root and
# throw-away copies of it, run with systemd-nspawn.
#
# Set before sourcing: repo (this checkout), cache (where the base root is kept).

# Root, debootstrap and systemd-nspawn; installs the last two with apt-get when missing.
roots_require() {
  if [ "$(id -u)" -ne 0 ]; then
    echo "$(basename "$0"): run as root (debootstrap and systemd-nspawn need it)" >&2
    exit 1
  fi
  if ! command -v debootstrap >/dev/null || ! command -v systemd-nspawn >/dev/null; then
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq debootstrap systemd-container
  fi
}

# The base root in $cache/bookworm-minbase: debootstrap's minbase with only python3,
# python3-venv and git (and the CA certificates git and pip need), made once.
roots_base() {
  base=$cache/bookworm-minbase
  if [ ! -x "$base/usr/bin/python3" ]; then
    echo "== debootstrap: Debian 12 minbase with python3, python3-venv, git into $base"
    rm -rf "$base"
    mkdir -p "$cache"
    debootstrap --variant=minbase --include=python3,python3-venv,git,ca-certificates \
      bookworm "$base" >"$cache/debootstrap.log" 2>&1 \
      || { tail -20 "$cache/debootstrap.log"; exit 1; }
  fi
}

# A fresh copy of the base in $root (under a new $work directory, removed at exit unless
# keep=yes; the logs in $work stay).
roots_copy() {
  work=$(mktemp -d "$cache/run.XXXXXX")
  root=$work/root
  trap roots_cleanup EXIT
  cp -a "$base" "$root"
  # A host behind a TLS-inspecting proxy (as some labs and CI workplaces are) needs its extra CAs
  # inside the root too, and pip must be told to use the system's bundle (roots_run sets
  # PIP_CERT): that is the network's setup, not the project's. Nothing else of the host's (pip
  # indexes, wheels, packages) is carried over.
  if compgen -G "/usr/local/share/ca-certificates/*.crt" >/dev/null; then
    cp /usr/local/share/ca-certificates/*.crt "$root/usr/local/share/ca-certificates/"
    roots_run update-ca-certificates >/dev/null 2>&1
  fi
}

roots_cleanup() {
  if [ -n "${roots_on_exit:-}" ]; then
    $roots_on_exit || true
  fi
  if [ "${keep:-no}" = yes ]; then
    echo "== kept the root: $root"
  else
    rm -rf "$root"
  fi
  echo "== logs: $work"
}

# Run a command in the (not booted) root as root, this checkout bound read-only at /src. nspawn
# mounts an empty tmpfs on /tmp; --register=no and --keep-unit: no machined or system bus needed.
roots_run() {
  systemd-nspawn --quiet --register=no --keep-unit --as-pid2 --directory="$root" \
    --bind-ro="$repo:/src" --setenv=HOME=/root --setenv=LANG=C.UTF-8 \
    --setenv=PIP_CERT=/etc/ssl/certs/ca-certificates.crt "$@"
}

# Run a bash script in the root, its output in $work/NAME.log; print its exit status, duration
# and closing lines. Returns the script's exit status.
roots_step() {
  local name=$1 script=$2
  local start=$SECONDS status=0
  echo "== $name"
  roots_run bash -c "$script" >"$work/$name.log" 2>&1 || status=$?
  echo "   exit status $status after $((SECONDS - start)) s; last lines:"
  # Without colours, the blank lines and nspawn's own notice about its propagation directory.
  sed 's/\x1b\[[0-9;?]*[a-zA-Z]//g' "$work/$name.log" | grep -v '^\s*$' \
    | grep -v '^Attempted to remove disk file system' | tail -n 8 | sed 's/^/   | /'
  return $status
}

# Shell text that clones /src to the directory $1 (git refuses a repository owned by another
# user unless it is named safe).
roots_clone() {
  echo "git config --global --add safe.directory /src && git config --global --add safe.directory /src/.git && git clone -q /src $1"
}
