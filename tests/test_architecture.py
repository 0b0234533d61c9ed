"""The layers of docs/architecture.md, as import-linter contracts (pyproject.toml
[tool.importlinter]): checked on the code, shown to catch an upward import, and the one rule
import-linter cannot see -- the CLI imports the layers below it only inside its commands."""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ["lab.cli", "lab.studies", "procedures", "drivers | estimation | sim_devices", "lab.core"]
BELOW_THE_CLI = ("lab.studies", "procedures", "drivers", "estimation", "sim_devices")


def _lint(cwd: Path, config: Path | None = None) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("lint-imports")
    cmd = [str(exe)] + (["--config", str(config)] if config else [])
    env = dict(os.environ, PYTHONPATH=str(cwd))
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env, timeout=300)


def _layers_contract() -> tuple[dict, dict]:
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    return cfg, next(c for c in cfg["contracts"] if c["type"] == "layers")


def test_the_import_contracts_hold():
    r = _lint(ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout


def test_the_layers_are_the_tree_with_no_exceptions_and_no_module_lists():
    cfg, layers = _layers_contract()
    assert layers["layers"] == LAYERS
    assert set(layers) == {"name", "type", "layers"}          # no ignore_imports, no containers
    for contract in cfg["contracts"]:
        assert not contract.get("ignore_imports"), contract["name"]
        assert "source_modules" not in contract, contract["name"]  # no hand-written lists of modules
    for layer in LAYERS:
        for module in layer.split(" | "):
            assert (ROOT / module.replace(".", "/") / "__init__.py").is_file(), module


# a toy tree with the project's packages, each layer importing the one below it (allowed)
TOY = {
    "lab/cli/__init__.py": "",
    "lab/cli/mod.py": "import lab.studies.mod\nimport procedures.mod\nimport lab.core.mod\n",
    "lab/studies/mod.py": "import procedures.mod\nimport estimation.mod\n",
    "procedures/mod.py": "import drivers.mod\nimport estimation.mod\nimport sim_devices.mod\n",
    "drivers/mod.py": "import lab.core.mod\n",
    "estimation/mod.py": "import lab.core.mod\n",
    "sim_devices/mod.py": "import lab.core.mod\n",
    "lab/core/mod.py": "",
}
UPWARD = {   # planted module: the import it gains
    "a study imports the CLI": ("lab/studies/mod.py", "import lab.cli\n"),
    "estimation imports the CLI": ("estimation/mod.py", "from lab.cli import mod\n"),
    "a procedure imports a study": ("procedures/mod.py", "import lab.studies.mod\n"),
    "a driver imports a procedure": ("drivers/mod.py", "import procedures.mod\n"),
    "the kernel imports estimation": ("lab/core/mod.py", "import estimation.mod\n"),
    "estimation imports the simulator": ("estimation/mod.py", "import sim_devices.mod\n"),
}


def _toy_tree(tmp_path: Path, plant: tuple[str, str] | None) -> Path:
    for rel, body in TOY.items():
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        for parent in path.relative_to(tmp_path).parents[:-1]:
            (tmp_path / parent / "__init__.py").touch()
        path.write_text(body + (plant[1] if plant and plant[0] == rel else ""))
    cfg, layers = _layers_contract()
    (tmp_path / "pyproject.toml").write_text(
        "[tool.importlinter]\nroot_packages = " + repr(cfg["root_packages"]).replace("'", '"') + "\n\n"
        "[[tool.importlinter.contracts]]\nname = \"layers\"\ntype = \"layers\"\nlayers = "
        + repr(layers["layers"]).replace("'", '"') + "\n")
    return tmp_path


def test_the_layers_contract_holds_on_a_toy_tree_importing_downward(tmp_path):
    r = _lint(_toy_tree(tmp_path, None))
    assert r.returncode == 0, r.stdout + r.stderr


@pytest.mark.parametrize("case", list(UPWARD))
def test_the_layers_contract_catches_a_planted_upward_import(tmp_path, case):
    module, line = UPWARD[case]
    r = _lint(_toy_tree(tmp_path, (module, line)))
    assert r.returncode != 0, r.stdout + r.stderr
    assert "BROKEN" in r.stdout and module.removesuffix(".py").replace("/", ".") in r.stdout, r.stdout


def test_the_cli_imports_the_layers_below_it_only_inside_its_commands():
    """Every command module of lab/cli/ imported and `lab --help`'s parser built, in a fresh
    process: no study, procedure, driver, estimator or simulator loaded, nor a heavy library (so
    `lab --help` stays fast).  import-linter sees imports, not where they stand; this sees both."""
    code = ("import importlib, pkgutil, sys, lab.cli\n"
            "for m in pkgutil.iter_modules(lab.cli.__path__): importlib.import_module('lab.cli.' + m.name)\n"
            "lab.cli.build_parser().format_help()\n"
            "print('\\n'.join(sorted(sys.modules)))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    loaded = r.stdout.split()
    assert "lab.cli.bench" in loaded and "lab.core.errors" in loaded
    below = [m for m in loaded if m.startswith(tuple(p + "." for p in BELOW_THE_CLI)) or m in BELOW_THE_CLI]
    assert below == [], f"imported at module level or while building the parser: {below}"
    heavy = [m for m in ("numpy", "scipy", "cv2", "gtsam", "matplotlib", "rerun") if m in loaded]
    assert heavy == [], heavy
