"""The engine never imports bpy: every module of lmdp_addon imports with bpy made unimportable."""
import subprocess
import sys
import textwrap

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

PROBE = textwrap.dedent("""
    import importlib, pkgutil, sys
    sys.modules["bpy"] = None          # any `import bpy` now raises ImportError
    sys.path.insert(0, {root!r})
    import lmdp_addon
    names = ["lmdp_addon"]
    for info in pkgutil.walk_packages(lmdp_addon.__path__, "lmdp_addon."):
        importlib.import_module(info.name)
        names.append(info.name)
    loaded = sorted(n for n in sys.modules if n == "bpy" or n.startswith("bpy."))
    assert loaded == ["bpy"], loaded   # only our None placeholder
    print("\\n".join(names))
""")


def run_probe(root):
    return subprocess.run([sys.executable, "-c", PROBE.format(root=str(root))],
                          capture_output=True, text=True, timeout=300)


def test_every_engine_module_imports_without_bpy():
    run = run_probe(ROOT)
    assert run.returncode == 0, run.stderr
    imported = set(run.stdout.split())
    on_disk = {".".join(("lmdp_addon",) + p.relative_to(ROOT / "lmdp_addon").with_suffix("").parts)
               for p in (ROOT / "lmdp_addon").rglob("*.py") if p.stem != "__init__"}
    assert on_disk <= imported, f"modules not imported by the probe: {sorted(on_disk - imported)}"


def test_probe_detects_a_module_that_imports_bpy(tmp_path):
    """The probe can fail: a copy of the package with one module importing bpy is refused."""
    package = tmp_path / "lmdp_addon"
    package.mkdir()
    (package / "__init__.py").write_text('"""copy"""\n')
    (package / "bad.py").write_text("import bpy\n")
    run = run_probe(tmp_path)
    assert run.returncode != 0
    assert "bpy" in run.stderr
