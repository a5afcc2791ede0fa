"""Download every wheel listed in blender_manifest.toml into ./wheels/ (used by `make extension`).

    python scripts/fetch_wheels.py [--manifest blender_manifest.toml] [--dest wheels]

The manifest is the single source of truth: each entry's file name gives the package, version and
platform, and ``pip download --no-deps --only-binary=:all: --python-version 3.11
--implementation cp --platform <tag>`` fetches exactly that file. Wheels already present are
kept. Fails (exit 1, one line) when a download fails or pip picks a different file.
Standard library only.
"""
import argparse
import os
import re
import subprocess
import sys
import tempfile
import tomllib

NETWORK_ERRORS = re.compile(
    r"NewConnectionError|Failed to establish a new connection|Temporary failure in name resolution|"
    r"Name or service not known|Network is unreachable|Connection refused|ProxyError|"
    r"Max retries exceeded|SSLError|ConnectTimeout|timed out", re.IGNORECASE)


def manifest_wheels(manifest_path):
    """Wheel paths of the manifest, relative to its directory (``./wheels/x.whl``)."""
    with open(manifest_path, "rb") as fh:
        return list(tomllib.load(fh).get("wheels", []))


def parse_wheel_name(filename):
    """``(distribution, version, python_tag, abi_tag, platform_tags)`` of a wheel file name."""
    parts = filename[:-len(".whl")].split("-")
    if len(parts) not in (5, 6):
        raise ValueError(f"not a wheel file name: {filename}")
    return parts[0], parts[1], parts[-3], parts[-2], parts[-1].split(".")


def download_command(python, filename, dest):
    distribution, version, python_tag, _abi, platforms = parse_wheel_name(filename)
    command = [python, "-m", "pip", "download", "--disable-pip-version-check", "--no-deps",
               "--only-binary=:all:", "--python-version", "3.11", "--implementation", "cp",
               "--dest", dest, f"{distribution}=={version}"]
    for platform in platforms:
        command += ["--platform", platform]
    return command


def fetch(manifest_path, dest, python=sys.executable):
    """Download missing wheels; return the list of wheel paths. Raises SystemExit with a message."""
    root = os.path.dirname(os.path.abspath(manifest_path))
    wheels = manifest_wheels(manifest_path)
    os.makedirs(dest, exist_ok=True)
    for relative in wheels:
        target = os.path.normpath(os.path.join(root, relative))
        filename = os.path.basename(target)
        if os.path.dirname(target) != os.path.abspath(dest):
            raise SystemExit(f"error: manifest wheel {relative} is not in {dest}/")
        if os.path.exists(target):
            continue
        with tempfile.TemporaryDirectory(dir=dest) as scratch:
            command = download_command(python, filename, scratch)
            print(f"lmdp: downloading {filename}", flush=True)
            run = subprocess.run(command, capture_output=True, text=True)
            if run.returncode != 0:
                output = run.stdout + run.stderr
                name = parse_wheel_name(filename)[0]
                if NETWORK_ERRORS.search(output):
                    raise SystemExit(f"error: could not download {name} ({filename}) from PyPI: "
                                     "check the network / proxy")
                raise SystemExit(f"error: pip download of {filename} failed:\n{output.strip()[-2000:]}")
            got = os.listdir(scratch)
            if filename not in got:
                raise SystemExit(f"error: pip picked {got} instead of {filename}: "
                                 "update the wheels list in blender_manifest.toml")
            os.replace(os.path.join(scratch, filename), target)
    return wheels


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--manifest", default="blender_manifest.toml")
    parser.add_argument("--dest", default="wheels")
    args = parser.parse_args(argv)
    wheels = fetch(args.manifest, args.dest)
    print(f"lmdp: {len(wheels)} wheels in {args.dest}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
