#!/usr/bin/env bash
# Check what `make` needs from the machine before anything is installed, and say what is
# missing in one line that names the Debian/Ubuntu packages to install.
#
#   scripts/check_env.sh            # CPython 3.11 with venv + the system libraries bpy links against
#   scripts/check_env.sh --no-libs  # CPython 3.11 only (packaging targets that never load bpy)
#
# Environment: PYTHON (default python3.11), LMDP_SKIP_ENV_CHECK=1 skips every check.
set -u

if [ "${LMDP_SKIP_ENV_CHECK:-0}" = "1" ]; then
    exit 0
fi

check_libs=1
if [ "${1:-}" = "--no-libs" ]; then
    check_libs=0
fi

python="${PYTHON:-python3.11}"

# -- CPython 3.11 with the venv module (Debian splits ensurepip into python3.11-venv) ----------
if ! command -v "$python" >/dev/null 2>&1 \
    || ! "$python" -c 'import sys, venv, ensurepip; sys.exit(sys.version_info[:2] != (3, 11))' >/dev/null 2>&1
then
    echo "error: CPython 3.11 with venv not found (looked for '$python'): install it, e.g. on Debian/Ubuntu: sudo apt-get install python3.11 python3.11-venv" >&2
    exit 1
fi

# -- shared libraries that bpy (headless Blender) links against ----------------------------------
if [ "$check_libs" = "1" ] && [ "$(uname -s)" = "Linux" ]; then
    libraries=(libX11.so.6 libXi.so.6 libXrender.so.1 libXfixes.so.3 libxkbcommon.so.0 libSM.so.6 libGL.so.1)
    packages=(libx11-6 libxi6 libxrender1 libxfixes3 libxkbcommon0 libsm6 libgl1)

    ldconfig_bin="$(command -v ldconfig 2>/dev/null || true)"
    for candidate in /sbin/ldconfig /usr/sbin/ldconfig; do
        if [ -z "$ldconfig_bin" ] && [ -x "$candidate" ]; then
            ldconfig_bin="$candidate"
        fi
    done
    if [ -z "$ldconfig_bin" ]; then
        # No dynamic-linker cache to ask: nothing reliable to check, bpy's import will tell.
        exit 0
    fi
    cache="$("$ldconfig_bin" -p 2>/dev/null || true)"

    missing_libs=()
    missing_packages=()
    for i in "${!libraries[@]}"; do
        lib="${libraries[$i]}"
        found=0
        if printf '%s\n' "$cache" | grep -qE "^[[:space:]]*${lib//./\\.}[[:space:]]"; then
            found=1
        fi
        IFS=':' read -r -a extra_dirs <<< "${LD_LIBRARY_PATH:-}"
        for dir in "${extra_dirs[@]}"; do
            if [ -n "$dir" ] && [ -e "$dir/$lib" ]; then
                found=1
            fi
        done
        if [ "$found" = "0" ]; then
            missing_libs+=("$lib")
            missing_packages+=("${packages[$i]}")
        fi
    done

    if [ "${#missing_libs[@]}" -gt 0 ]; then
        echo "error: bpy (headless Blender) needs system libraries that are missing (${missing_libs[*]}): install them, e.g. on Debian/Ubuntu: sudo apt-get install ${missing_packages[*]}" >&2
        exit 1
    fi
fi

exit 0
