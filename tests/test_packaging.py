"""What a user installing the package meets: the version, the licence, the commands'
names in their usage text, strict JSON, and the public API of ``design``."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import design
import identify
from identify.jsonio import dumps, jsonable, write_json

ROOT = Path(__file__).resolve().parents[1]


def test_version_is_the_installed_distribution_s():
    from importlib.metadata import version

    assert identify.__version__ == version("nanofrictor") == design.__version__


@pytest.mark.parametrize("package", ["identify", "design"])
def test_version_flag_and_usage_name_the_command_run(package):
    out = subprocess.run([sys.executable, "-m", package, "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == f"python -m {package} (nanofrictor) {identify.__version__}"
    usage = subprocess.run([sys.executable, "-m", package, "--help"], capture_output=True, text=True).stdout
    assert usage.startswith(f"usage: python -m {package} ")


def test_the_licence_declared_is_shipped():
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License")
    assert 'license = { text = "MIT" }' in (ROOT / "pyproject.toml").read_text()


def test_design_exports_experiment_design():
    for name in ("design_experiment", "verify_plans", "ExperimentPlan", "Candidate", "paper_plan"):
        assert name in design.__all__ and callable(getattr(design, name))


def test_strict_json_writes_null_for_what_json_cannot_hold(tmp_path):
    data = dict(a=float("nan"), b=[np.inf, -np.inf, np.float32(1.5)], c=np.arange(3), d=np.int64(4),
                e=(1, 2), f=tmp_path, nested=dict(x=np.float64("nan")))
    out = json.loads(dumps(data), parse_constant=lambda c: pytest.fail(f"non-strict constant {c}"))
    assert out == dict(a=None, b=[None, None, 1.5], c=[0, 1, 2], d=4, e=[1, 2], f=str(tmp_path),
                       nested=dict(x=None))
    path = write_json(tmp_path / "deep" / "x.json", data)
    assert json.loads(path.read_text()) == out
    assert jsonable(math.nan) is None and jsonable("text") == "text"
