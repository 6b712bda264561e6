# Sourced (not run) by scripts/case_study.sh and scripts/test.sh: make .venv/ ready, then set
# the ROS environment every run needs.
#
# - Creates .venv/ in the repository root with python3.11 (or python3 if that is 3.11+) and
#   upgrades pip, on creation only.
# - Installs requirements-dev.txt and this package (uv pip install -e ., or pip where uv cannot
#   be had), unless the stamp file .venv/.hrc_bootstrap holds the hash of requirements*.txt,
#   setup.py, setup.cfg and package.xml, i.e. nothing that decides the install changed since
#   the last one.
# - Puts .venv/bin first on PATH and exports ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, so that
#   nodes started by a run only discover each other on this host.
#
# The caller sets ROS_DOMAIN_ID (tests: one per run; the case study: a fixed one).
# Set HRC_BOOTSTRAP_FORCE=1 to reinstall even if the stamp matches, HRC_BOOTSTRAP_PIP=1 to
# install with pip alone (uv, below, is the default where it can be had and works).

HRC_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
HRC_VENV="$HRC_ROOT/.venv"

_hrc_say() { printf '[bootstrap] %s\n' "$*" >&2; }
_hrc_die() { _hrc_say "error: $*"; return 1; }

_hrc_find_python() {
  local candidate
  for candidate in python3.11 python3; do
    if command -v "$candidate" >/dev/null 2>&1 &&
       "$candidate" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
      command -v "$candidate"
      return 0
    fi
  done
  return 1
}

# Hash of everything that decides what gets installed (and of the interpreter's version).
_hrc_install_hash() {
  (cd "$HRC_ROOT" && "$HRC_VENV/bin/python" - requirements*.txt setup.py setup.cfg package.xml <<'EOF'
import hashlib, sys
digest = hashlib.sha256(sys.version.encode())
for name in sys.argv[1:]:
    with open(name, 'rb') as handle:
        digest.update(name.encode() + b'\0' + handle.read() + b'\0')
print(digest.hexdigest())
EOF
  )
}

# uv installs what pip would, from the same indexes, in a fraction of the time (20 s against
# 70 s for this package's 230 distributions on the 2-core machine with an empty cache; 72 s
# against 256-357 s at load 8: bench/README.md, "The fresh clone's install"). uv itself is a
# wheel from the package index (requirements-bootstrap.txt, pinned), put into .venv; its flags
# are pip's own settings as pip's parser reads them (scripts/uv_flags.py). Returns non-zero
# (and the caller installs with pip) where uv cannot be had, pip is set up in a way uv would
# not follow, or uv's install fails or leaves hrc_ros unusable. HRC_BOOTSTRAP_PIP=1 skips uv.
_hrc_uv_install() {
  local out line flags=() envs=()
  "$HRC_VENV/bin/python" -m pip install --quiet --progress-bar off --timeout 20 --retries 1 \
      -r "$HRC_ROOT/requirements-bootstrap.txt" >/dev/null 2>&1 ||
    { _hrc_say "uv is not installable here; pip installs"; return 1; }
  out="$("$HRC_VENV/bin/python" "$HRC_ROOT/scripts/uv_flags.py")" ||
    { _hrc_say "pip installs (above)"; return 1; }
  while IFS= read -r line; do
    if [[ "$line" == "env "* ]]; then envs+=("${line#env }"); else flags+=("$line"); fi
  done <<<"$out"
  _hrc_say "installing requirements-dev.txt and hrc_ros (uv pip install -e .) into .venv"
  if ! env "${envs[@]}" "$HRC_VENV/bin/uv" pip install --quiet \
      --python "$HRC_VENV/bin/python" "${flags[@]}" \
      -r "$HRC_ROOT/requirements-dev.txt" -e "$HRC_ROOT"; then
    _hrc_say "uv pip install failed (above); pip installs instead"
    return 1
  fi
  _hrc_check_install 2>/dev/null || { _hrc_say "uv's install is not usable; pip installs"; return 1; }
}

# The editable install must put the console scripts in .venv/bin (not setup.cfg's script_dir,
# which is for colcon) and make the package importable from anywhere.
_hrc_check_install() {
  [ -x "$HRC_VENV/bin/hrc-solve" ] ||
    _hrc_die "the install did not create .venv/bin/hrc-solve" || return 1
  (cd / && "$HRC_VENV/bin/python" -c 'import hrc_ros') ||
    _hrc_die "hrc_ros is not importable after the install" || return 1
}

_hrc_bootstrap() {
  local python stamp want started
  started=$SECONDS
  stamp="$HRC_VENV/.hrc_bootstrap"

  # A venv whose interpreter no longer runs (moved clone, removed Python) is rebuilt.
  if [ -e "$HRC_VENV" ] && ! "$HRC_VENV/bin/python" -c '' >/dev/null 2>&1; then
    _hrc_say "$HRC_VENV is broken; recreating it"
    rm -rf "$HRC_VENV"
  fi
  if [ ! -x "$HRC_VENV/bin/python" ]; then
    python="$(_hrc_find_python)" ||
      _hrc_die "needs Python 3.11 or newer as python3.11 or python3" || return 1
    _hrc_say "creating .venv with $python ($("$python" --version 2>&1))"
    "$python" -m venv "$HRC_VENV" ||
      _hrc_die "'$python -m venv' failed (on Debian/Ubuntu: apt-get install python3-venv)" ||
      return 1
    "$HRC_VENV/bin/python" -m pip install --quiet --upgrade pip || return 1
  fi

  want="$(_hrc_install_hash)" || return 1
  if [ -z "${HRC_BOOTSTRAP_FORCE:-}" ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] &&
     [ -x "$HRC_VENV/bin/hrc-solve" ]; then
    _hrc_say ".venv up to date"
    return 0
  fi

  rm -f "$stamp"
  if [ -n "${HRC_BOOTSTRAP_PIP:-}" ] || ! _hrc_uv_install; then
    _hrc_say "installing requirements-dev.txt and hrc_ros (pip install -e .) into .venv"
    "$HRC_VENV/bin/python" -m pip install --quiet --progress-bar off \
        -r "$HRC_ROOT/requirements-dev.txt" -e "$HRC_ROOT" || return 1
    _hrc_check_install || return 1
  fi
  printf '%s\n' "$want" >"$stamp"
  _hrc_say "installed in $((SECONDS - started)) s"
}

# Serialise concurrent bootstraps of one clone (test.sh and case_study.sh at once): lock the
# repository directory itself, so no lock file is left behind.
if command -v flock >/dev/null 2>&1 && exec {_hrc_lock_fd}<"$HRC_ROOT"; then
  flock "$_hrc_lock_fd"
  _hrc_status=0
  _hrc_bootstrap || _hrc_status=$?
  exec {_hrc_lock_fd}<&-
else
  _hrc_status=0
  _hrc_bootstrap || _hrc_status=$?
fi
if [ "$_hrc_status" -ne 0 ]; then
  _hrc_say "failed"
  return "$_hrc_status" 2>/dev/null || exit "$_hrc_status"
fi

export PATH="$HRC_VENV/bin:$PATH"
export VIRTUAL_ENV="$HRC_VENV"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
unset _hrc_status _hrc_lock_fd
