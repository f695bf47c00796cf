"""The lean core: what ``import anm_torchrl`` and the main job import, and the errors of a missing extra.

Each check runs in a fresh interpreter (``sys.modules`` of the test process already holds everything).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

from anm_torchrl._extras import EXTRAS, MissingExtraError, install_hint, require

ROOT = Path(__file__).resolve().parents[1]
#: behind an extra: the main job (``recipes/ppo.py surrogate=pinn``) must import none of them
OPTIONAL = sorted(EXTRAS)


def run_python(code: str, timeout: float = 240) -> subprocess.CompletedProcess:
    """``code`` in a fresh interpreter with this checkout first on the path; fails the test on a non-zero exit."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, env=env,
                         timeout=timeout, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    return out


def block(modules: list[str]) -> str:
    """Code that makes ``import m`` fail with ModuleNotFoundError for every ``m`` (as if not installed)."""
    return f"import sys\nfor _m in {modules!r}:\n    sys.modules[_m] = None\n"


def test_import_anm_torchrl_is_light_and_registers_nothing():
    out = run_python("""
        import sys
        import anm_torchrl
        assert anm_torchrl.__version__
        heavy = [m for m in ("torch", "torchrl", "gymnasium", "numpy", "matplotlib") if m in sys.modules]
        assert not heavy, heavy
        import gymnasium
        assert not [k for k in gymnasium.registry if k.startswith("anm_torchrl/")]
        anm_torchrl.gym  # the lazy subpackage registers the ids
        print(" ".join(sorted(k for k in gymnasium.registry if k.startswith("anm_torchrl/"))))
    """)
    ids = out.stdout.split()
    assert "anm_torchrl/ANM6Easy-v0" in ids and "anm_torchrl/ANM-v0" in ids, ids


def test_the_main_job_imports_and_runs_without_any_extra(tmp_path):
    # 1. the modules the main job (recipes/ppo.py surrogate=pinn) imports up front and on the way (env, PINN,
    #    baselines for the reward scale, evaluation, rendering, gymnasium adapters) import no optional package;
    # 2. with every optional package then made unimportable, a smoke PINN (seconds) and a few PPO frames run:
    #    the core is extras-free at run time too, not only at import time. One interpreter: torch imports once.
    out = run_python(f"""
import sys
import anm_torchrl
from anm_torchrl import make_env
import anm_torchrl.baselines, anm_torchrl.envs, anm_torchrl.gym.env, anm_torchrl.gym.vector
import anm_torchrl.networks, anm_torchrl.render, anm_torchrl.surrogates.pinn, anm_torchrl.surrogates.registry
import anm_torchrl.evaluation, anm_torchrl.training.factory, anm_torchrl.training.protocol
import anm_torchrl.training.algorithms.ppo
print("optional imported:", sorted({{m.split(".")[0] for m in sys.modules}} & set({OPTIONAL!r})))
""" + block(OPTIONAL) + f"""
import torch
from anm_torchrl.networks import ANM6_EASY, simulator as network_simulator
from anm_torchrl.surrogates.pinn import cache, presets
from anm_torchrl.training.protocol import train as train_ppo
from tests.recipe_utils import compose
torch.set_num_threads(1)
pinn = cache.train_and_save(presets.preset("smoke"), network_simulator(ANM6_EASY), path={str(tmp_path / "pinn")!r})[0]
cfg = compose("config", ["surrogate=pinn", "surrogate.path=" + str(pinn), "env.num_envs=4",
                         "collector.frames_per_batch=32", "collector.total_frames=32", "loss.mini_batch_size=16",
                         "eval.num_episodes=2", "eval.test_episodes=2", "eval.max_steps=5", "logger.backend=null",
                         "logger.progress=false"])
train_ppo(cfg, {str(tmp_path / "run")!r})
""", timeout=400)
    assert "optional imported: []" in out.stdout
    assert (tmp_path / "run" / "summary.json").is_file()


def test_sb3_adapter_without_its_extra_names_it_before_importing_torch():
    out = run_python(block(["stable_baselines3"]) + """
import sys
from anm_torchrl._extras import MissingExtraError
try:
    import anm_torchrl.gym.sb3
except MissingExtraError as e:
    print(e)
    print("torch imported:", "torch" in sys.modules)
""")
    assert "pip install -e '.[sb3]'" in out.stdout and "torch imported: False" in out.stdout


@pytest.mark.parametrize("module", OPTIONAL)
def test_require_names_the_extra(module, monkeypatch):
    monkeypatch.setitem(sys.modules, module, None)  # import fails as if the package were not installed
    extra = EXTRAS[module][0]
    with pytest.raises(MissingExtraError, match=rf"{module!r}.*{extra!r} extra: " + install_hint(extra)
                       .replace("[", r"\[").replace("]", r"\]").replace(".", r"\.")) as err:
        require(module)
    assert isinstance(err.value, ImportError) and isinstance(err.value.__cause__, ModuleNotFoundError)


def test_every_extra_named_exists_in_pyproject():
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert {extra for extra, _ in EXTRAS.values()} <= set(extras)
    assert "anm_torchrl[all]" in extras["test"]  # CI's `pip install -e '.[test]'` pulls every extra
    named = {e for spec in extras["all"] for e in spec.split("[")[1].rstrip("]").split(",")}
    assert named == set(extras) - {"all", "test"}


def test_torchrl_log_lines_carry_no_ansi_codes_when_redirected():
    # TorchRL's console handler colours every line; a redirected run (``> ppo.log``) must get plain text
    out = run_python("""
        import logging
        import anm_torchrl.training.factory  # noqa: F401  (what every recipe imports)
        logging.getLogger("torchrl").info("hello")
    """)
    assert "[torchrl][INFO] hello" in out.stdout and "\\x1b" not in out.stdout
