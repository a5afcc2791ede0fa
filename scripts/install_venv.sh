#!/usr/bin/env bash
# Create VENV with CPython 3.11 if it is missing and make its packages exactly the pinned set.
#
#   scripts/install_venv.sh VENV REQUIREMENTS
#
# Installs with --no-deps (so nothing unpinned can come in), runs `pip check`, removes packages
# that are installed but not pinned, and fails unless `pip freeze` equals the pins.
# A download failure is reported in one line: "could not download X from PyPI: check the network / proxy".
set -euo pipefail

venv="${1:?usage: install_venv.sh VENV REQUIREMENTS}"
requirements="${2:?usage: install_venv.sh VENV REQUIREMENTS}"
python="${PYTHON:-python3.11}"
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"

if [ -x "$venv/bin/python" ] && ! "$venv/bin/python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
    echo "lmdp: $venv is not a working CPython 3.11 venv: recreating it"
    rm -rf "$venv"
fi
if [ ! -x "$venv/bin/python" ]; then
    echo "lmdp: creating $venv with $python"
    if ! "$python" -m venv "$venv"; then
        echo "error: '$python -m venv' failed: install the venv module, e.g. on Debian/Ubuntu: sudo apt-get install python3.11 python3.11-venv" >&2
        exit 1
    fi
fi

log="$venv/pip-install.log"
echo "lmdp: installing the pinned packages of $requirements into $venv (log: $log)"
if ! "$venv/bin/python" -m pip install --disable-pip-version-check --no-deps --only-binary=:all: \
        -r "$requirements" >"$log" 2>&1; then
    package="$(sed -n 's/.*No matching distribution found for \([^ ]*\).*/\1/p' "$log" | head -n 1)"
    if [ -n "$package" ]; then
        # pip only says why it found nothing at debug verbosity (when it does not retry): ask again.
        diagnose="$(mktemp -d)"
        "$venv/bin/python" -m pip download --disable-pip-version-check --no-deps --only-binary=:all: \
            -vvv --dest "$diagnose" "$package" >>"$log" 2>&1 || true
        rm -rf "$diagnose"
    fi
    if grep -qiE 'NewConnectionError|Failed to establish a new connection|Temporary failure in name resolution|Name or service not known|No address associated|Network is unreachable|Connection refused|ConnectTimeout|timed out|ProxyError|Max retries exceeded|SSLError|Could not fetch URL|ConnectionError' "$log"; then
        echo "error: could not download ${package:-the pinned packages} from PyPI: check the network / proxy (pip's log: $log)" >&2
    elif [ -n "$package" ]; then
        echo "error: PyPI has no $package for this machine (CPython 3.11, $(uname -s) $(uname -m)): see $log" >&2
    else
        echo "error: pip install -r $requirements failed; last lines of $log:" >&2
        tail -n 5 "$log" >&2
    fi
    exit 1
fi

if ! "$venv/bin/python" -m pip check >>"$log" 2>&1; then
    echo "error: the pinned packages do not satisfy each other's requirements (pip check):" >&2
    "$venv/bin/python" -m pip check >&2 || true
    exit 1
fi

extras="$("$python" "$here/pins.py" extras "$venv/bin/python" "$requirements")"
if [ -n "$extras" ]; then
    echo "lmdp: removing packages that are not pinned: $extras"
    # shellcheck disable=SC2086
    "$venv/bin/python" -m pip uninstall --disable-pip-version-check -y $extras >>"$log" 2>&1
fi

if ! "$python" "$here/pins.py" check "$venv/bin/python" "$requirements"; then
    echo "error: $venv does not hold exactly the pinned packages (see above)" >&2
    exit 1
fi
echo "lmdp: $venv matches $requirements"
