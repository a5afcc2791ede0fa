"""Pinned requirements: read them, compare them with a venv, make the venv match.

    python scripts/pins.py check VENV_PYTHON REQUIREMENTS   # exit 1 and list differences
    python scripts/pins.py extras VENV_PYTHON REQUIREMENTS  # print installed names not pinned

Standard library only: it runs before the venv has anything in it.
"""
import os
import re
import subprocess
import sys


def normalise(name):
    """PEP 503 name normalisation: ``Cython`` == ``cython``, ``python_dateutil`` == ``python-dateutil``."""
    return re.sub(r"[-_.]+", "-", name).lower()


def read_pins(path):
    """``{normalised name: version}`` of a requirements file, following ``-r`` includes.

    Raises ``ValueError`` for any line that is not an exact ``name==version`` pin.
    """
    pins = {}
    with open(path, encoding="utf-8") as fh:
        for number, raw in enumerate(fh, 1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            if line.startswith(("-r ", "--requirement ")):
                include = line.split(None, 1)[1].strip()
                pins.update(read_pins(os.path.join(os.path.dirname(path), include)))
                continue
            match = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)==([A-Za-z0-9.+!-]+)", line)
            if not match:
                raise ValueError(f"{path}:{number}: not an exact pin (name==version): {line!r}")
            pins[normalise(match.group(1))] = match.group(2)
    return pins


def frozen(python):
    """``{normalised name: version}`` that ``python -m pip freeze`` reports."""
    out = subprocess.run([python, "-m", "pip", "freeze", "--disable-pip-version-check"],
                         check=True, capture_output=True, text=True).stdout
    installed = {}
    for line in out.splitlines():
        name, sep, version = line.strip().partition("==")
        if sep:
            installed[normalise(name)] = version
        elif line.strip():
            installed[normalise(line.strip())] = "?"  # editable or URL installs are never pinned
    return installed


def differences(pins, installed):
    """Human-readable differences between the pins and what is installed (empty when equal)."""
    lines = []
    for name in sorted(pins.keys() | installed.keys()):
        want, have = pins.get(name), installed.get(name)
        if want is None:
            lines.append(f"{name}=={have} is installed but not pinned")
        elif have is None:
            lines.append(f"{name}=={want} is pinned but not installed")
        elif want != have:
            lines.append(f"{name} is {have}, pinned {want}")
    return lines


def main(argv):
    if len(argv) != 4 or argv[1] not in ("check", "extras"):
        print(__doc__, file=sys.stderr)
        return 2
    command, python, requirements = argv[1:]
    pins = read_pins(requirements)
    installed = frozen(python)
    if command == "extras":
        print(" ".join(sorted(installed.keys() - pins.keys())))
        return 0
    diff = differences(pins, installed)
    for line in diff:
        print(f"  {line}", file=sys.stderr)
    return 1 if diff else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
