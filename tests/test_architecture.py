"""The layers of docs/architecture.md, as import-linter contracts (pyproject.toml
[tool.importlinter]): checked on the code, and shown to catch a violation."""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _lint(cwd: Path, config: Path | None = None) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("lint-imports")
    cmd = [str(exe)] + (["--config", str(config)] if config else [])
    env = dict(os.environ, PYTHONPATH=str(cwd))
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env, timeout=300)


def test_the_import_contracts_hold():
    r = _lint(ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout


def test_the_layers_contract_catches_estimation_reaching_into_the_simulator(tmp_path):
    """The same layers contract on a toy tree whose estimation imports the simulator: broken."""
    for pkg, body in {"lab": "", "drivers": "", "sim_devices": "", "procedures": "",
                      "estimation": "from sim_devices import render\n"}.items():
        (tmp_path / pkg).mkdir()
        (tmp_path / pkg / "__init__.py").write_text("")
        (tmp_path / pkg / "mod.py").write_text(body)
    (tmp_path / "sim_devices" / "render.py").write_text("")
    (tmp_path / "lab" / "cli").mkdir()
    (tmp_path / "lab" / "cli" / "__init__.py").write_text("import procedures.mod\nimport drivers.mod\n"
                                                          "import estimation.mod\nimport sim_devices.mod\n")
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    layers = next(c for c in cfg["contracts"] if c["type"] == "layers")
    toml = ("[tool.importlinter]\nroot_packages = " + repr(cfg["root_packages"]).replace("'", '"') + "\n\n"
            "[[tool.importlinter.contracts]]\nname = \"layers\"\ntype = \"layers\"\nlayers = "
            + repr(layers["layers"]).replace("'", '"') + "\n"
            'ignore_imports = ["lab.cli -> procedures.mod", "lab.cli -> drivers.mod", "lab.cli -> estimation.mod", '
            '"lab.cli -> sim_devices.mod"]\n')
    (tmp_path / "pyproject.toml").write_text(toml)
    r = _lint(tmp_path)
    assert r.returncode != 0, r.stdout + r.stderr
    assert "estimation.mod -> sim_devices.render" in r.stdout or "estimation is not allowed to import sim_devices" in r.stdout
