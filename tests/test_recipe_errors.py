"""A user's mistake in any recipe is one line naming it (no traceback), exit status 1, and no run directory.

Each recipe checks its config, network, device and checkpoint inside ``training.recipe_errors.user_errors``
before heavy work; the subprocess tests run the real scripts as a user types them, in an empty folder.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from anm_torchrl.training.recipe_errors import (NotWritableError, check_artifact_cache, check_device, check_writable,
                                                remove_hydra_only_dir, user_errors)

ROOT = Path(__file__).resolve().parents[1]


def test_user_errors_is_one_line_and_removes_a_hydra_only_dir(tmp_path):
    run_dir = tmp_path / "outputs" / "job" / "2026-12-04" / "10-00-00"
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / "job.log").write_text("")
    with pytest.raises(SystemExit, match=r"^job\.py: size must be an integer >= 1, got 0$"):
        with user_errors("job.py", run_dir):
            raise ValueError("size must be an integer >= 1, got 0")
    assert not (tmp_path / "outputs").exists()  # the empty Hydra levels went with it
    with pytest.raises(SystemExit, match=r"^job\.py: 'x' missing$"):  # a KeyError's message, unquoted twice
        with user_errors("job.py"):
            raise KeyError("'x' missing")
    with pytest.raises(RuntimeError):  # not a user's mistake: the traceback stays
        with user_errors("job.py"):
            raise RuntimeError("a bug")


def test_a_run_dir_with_work_in_it_is_kept(tmp_path):
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    remove_hydra_only_dir(run_dir)
    assert (run_dir / "checkpoints").is_dir()


def test_added_keys_are_refused_outside_the_groups_a_recipe_passes_on():
    """``+key=`` is refused where the recipe would not read the key, and allowed in a group whose every key the
    recipe passes on (a review found ``train_surrogate.py +models.dt.max_leaf_nodes=8`` and ``ppo.py
    +surrogate.n_jobs=2`` refused, though the estimator and the loader take them); ``++key=`` is Hydra's override."""
    from anm_torchrl.training.recipe_errors import refuse_appended_keys

    refuse_appended_keys("ppo.py", ["network=case33bw", "++env.num_envs=8", "+surrogate.n_jobs=2"], ("surrogate",))
    refuse_appended_keys("train_surrogate.py", ["+models.dt.max_leaf_nodes=8"], ("models",))
    with pytest.raises(ValueError, match=r"^\+surrogates.n_jobs=2: 'surrogates.n_jobs' is not one of this recipe"):
        refuse_appended_keys("ppo.py", ["+surrogates.n_jobs=2"], ("surrogate",))  # a prefix, not a substring


def test_check_device():
    check_device("cpu")
    with pytest.raises(ValueError, match="env.device: 'gpu0' is not a torch device"):
        check_device("gpu0")
    import torch

    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="env.device=cuda:0: this torch build .* has no usable CUDA device"):
            check_device("cuda:0")


def test_check_writable_and_artifact_cache(monkeypatch, tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    check_writable(tmp_path / "new" / "dir", "render_dir")  # creatable: fine, and nothing is created
    assert not (tmp_path / "new").exists()
    with pytest.raises(NotWritableError, match=r"^render_dir=.*a_file/ep: cannot write there \(.*a_file is not a"):
        check_writable(a_file / "ep", "render_dir")
    monkeypatch.setenv("ANM_TORCHRL_HOME", str(a_file / "home"))
    check_artifact_cache({"name": "none"})  # the true simulator, or an explicit path, needs no cache
    check_artifact_cache({"name": "pinn", "path": "model.safetensors"})
    with pytest.raises(NotWritableError, match="cannot write the artifact cache .*set ANM_TORCHRL_HOME"):
        check_artifact_cache({"name": "pinn", "path": None})


@pytest.mark.parametrize("recipe", ["evaluate", "ppo"])
def test_a_damaged_network_file_is_one_line(recipe, tmp_path):
    """A network file that exists but lacks an entry: evaluate.py printed a traceback (it loads the network outside
    its error handling); every recipe names the file and what it lacks."""
    import numpy as np

    from anm_torchrl.networks import get_network, save_network

    case = get_network("case33bw")
    good = save_network(tmp_path / "good.npz", case.network, case.load_p, case.gen_p_max)
    with np.load(good, allow_pickle=False) as data:
        np.savez(tmp_path / "broken.npz", **{k: data[k] for k in data.files if k != "gen_p_max"})
    extra = ["policy=do_nothing", "steps=5", "episodes=1"] if recipe == "evaluate" else []
    out = subprocess.run([sys.executable, str(ROOT / "recipes" / f"{recipe}.py"), "network=broken.npz", *extra],
                         cwd=tmp_path, capture_output=True, text=True, timeout=300,
                         env={**os.environ, "ANM_TORCHRL_HOME": str(tmp_path / "home"), "HYDRA_FULL_ERROR": "0"})
    assert out.returncode == 1 and "Traceback" not in out.stderr + out.stdout, out.stderr[-2000:]
    last = out.stderr.strip().splitlines()[-1]
    assert re.fullmatch(rf"{recipe}.py: .*broken.npz: network file without \['gen_p_max'\]", last), last


@pytest.mark.parametrize("recipe, args, message", [
    ("make_dataset", "generative.chunk=0", "generative.chunk must be an integer >= 1, got 0"),
    ("train_surrogate", "network=case34bw", "unknown network 'case34bw'"),
    ("reproduce", "preset.experiments=[nope]", "unknown experiment 'nope'"),
    ("sac", "checkpoint.resume=missing.pt", "checkpoint.resume: no file"),
    ("ppo", "checkpoint.init_from=missing.pt", "checkpoint.init_from: no file"),
    ("ppo", "checkpoint.resume=a.pt checkpoint.init_from=b.pt", "checkpoint.resume and checkpoint.init_from: give one"),
    # a surrogate choice that failed once the run had started (a traceback, a Hydra-only run directory left)
    ("ppo", "surrogate=gym_anm network=case33bw", "surrogate=gym_anm runs gym-anm's ANM6Easy only"),
    ("ppo", "surrogate=xgb surrogate.dataset=nope", "surrogate.dataset must be one of generative, agent; got 'nope'"),
    # another recipe's model group: a TypeError traceback after the run had started, before
    ("ppo", "model=pinn", r"model.dynamics is not a setting of ppo.py's models: ppo.py takes model=default"),
    ("sac", "model=default", r"model.state_dependent_scale is not a setting of sac.py.s models: .* model=sac"),
    # relative to where the command is typed (was: to the run directory, then a FileNotFoundError traceback)
    ("ppo", "surrogate=pinn surrogate.path=mypinn", r"surrogate.path: nothing at .*/test_recipe_prints\w*/mypinn$"),
    ("evaluate", "policy=mpc_perfect policy_kwargs.horizon=-1 steps=5 episodes=1", "horizon must be an integer >= 1"),
    ("evaluate", "policy=do_nothing render=true render_dir={tmp}/a_file/ep steps=5 episodes=1",
     r"render_dir=.*/a_file/ep: cannot write there \(.*/a_file is not a folder\)"),
    ("ppo", "ANM_TORCHRL_HOME={tmp}/a_file/home surrogate=pinn collector.total_frames=1000",
     r"cannot write the artifact cache .*/a_file/home .*set ANM_TORCHRL_HOME to a writable folder"),
    ("train_pinn", "pinn_preset=smoke", "preset 'smoke' has no acceptance bar"),  # into the default cache
    # a folder under a regular file, an existing dataset: a traceback and a run directory before
    ("train_pinn", "pinn_preset=smoke path={tmp}/a_file/x", r"path=.*/a_file/x: cannot write there"),
    ("train_pinn", "eval_only=true path={tmp}/nopinn", r"no trained PINN at .*/nopinn/pinn.safetensors"),
    ("make_dataset", "dataset=agent size=100 out={tmp}/a_file/ds", r"out=.*/a_file/ds: cannot write there"),
    ("make_dataset", "dataset=agent size=100 out={tmp}", r"out=.* exists; pass overwrite=true to replace it"),
    # a user's folder is never replaced (overwrite=true emptied any folder named by out=)
    ("make_dataset", "dataset=agent size=100 out={tmp} overwrite=true", r"is a folder that is not a saved"),
    ("reproduce", "threads=0", "threads must be an integer >= 1, got 0"),  # a RuntimeError traceback before
    ("reproduce", "preset=tiny preset.experiments=[speed] preset.speed.repeats=-1",  # no median, after the run
     r"preset.speed.repeats must be an integer >= 1 \(or a list of them\), got -1"),
    ("reproduce", "report_only=true out_dir={tmp}/norun", r"out_dir=.*/norun holds no run.json"),
    ("evaluate", "policy=mpc_perfect policy_kwargs.bogus=1 steps=5 episodes=1",
     r"MPC options \['bogus'\] are not settings of the '\w+' solver"),  # was an AttributeError at the first step
    # Hydra's advice for an unknown key (+key=value) ran the job with the key ignored, in every recipe
    *[(recipe, "+loss.gama=0.9" + extra, r"\+loss.gama=0.9: 'loss.gama' is not one of this recipe's keys \(an "
       rf"added key is not read\); python recipes/{recipe}.py --help")
      for recipe, extra in [("ppo", ""), ("sac", ""), ("shac", ""), ("make_dataset", ""), ("train_pinn", ""),
                            ("train_surrogate", " surrogate=lr"), ("reproduce", "")]],
    # ``++`` (set or add) added a misspelt key without a word, recorded in summary.json as if it had been used
    ("shac", "++loss.horizn=8", r"\+\+loss.horizn=8: 'loss.horizn' is not one of this recipe's keys"),
    ("make_dataset", "++generative.chnk=2", r"'generative.chnk' is not one of this recipe's keys"),
    # the PINN's options: a traceback from inside the run (and its directory left) before
    ("shac", "model=pinn surrogate=pinn surrogate.terminal=nosuch", "terminal must be one of"),
    ("ppo", "surrogate=pinn surrogate.residual_threshold=-1", "residual_threshold"),
    ("ppo", "surrogate=pinn +surrogate.terminall=physics", "'terminall' is not an option of the PINN surrogate"),
    # another recipe's model group: a 30-line Hydra traceback (the run directory names model.dynamics)
    ("shac", "model=sac", "shac.py takes model=exact or model=pinn"),
    ("shac", "model=default", "shac.py takes model=exact or model=pinn"),
])
def test_recipe_prints_one_line(recipe, args, message, tmp_path):
    """``args`` as typed after ``python recipes/<recipe>.py`` (``NAME=value`` of an upper-case NAME sets that
    environment variable; ``{tmp}`` is the test's folder, holding a regular file ``a_file``); ``message`` a regex."""
    (tmp_path / "a_file").write_text("")  # nothing can be created under it
    env = {**os.environ, "ANM_TORCHRL_HOME": str(tmp_path / "home"), "HYDRA_FULL_ERROR": "0", "OMP_NUM_THREADS": "1"}
    argv = [a.format(tmp=tmp_path) for a in args.split()]
    env.update(a.split("=", 1) for a in argv if a.split("=", 1)[0].isupper())
    argv = [a for a in argv if not a.split("=", 1)[0].isupper()]
    out = subprocess.run([sys.executable, str(ROOT / "recipes" / f"{recipe}.py"), *argv], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 1, out.stderr
    assert "Traceback" not in out.stderr + out.stdout
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith(f"{recipe}.py: ") and re.search(message, last), last
    assert not (tmp_path / "outputs").exists(), list((tmp_path / "outputs").rglob("*"))


LIGHT = """
import runpy, sys
sys.argv = sys.argv[1:]
try:
    runpy.run_path(sys.argv[0], run_name="__main__")
except SystemExit as stop:  # a user error: its one line, as the interpreter would print it
    print(stop.code, file=sys.stderr)
finally:
    print("heavy modules imported:", sorted(m for m in ("torch", "numba", "tensordict") if m in sys.modules))
"""


@pytest.mark.parametrize("recipe, args", [
    ("ppo", "network=case34bw"), ("sac", "network=case34bw"), ("shac", "network=case34bw"),
    # out-of-range values (they imported torch through the activation names before)
    ("ppo", "loss.gamma=2"), ("sac", "replay.size=-5"), ("shac", "loss.horizon=0"),
    ("make_dataset", "generative.chunk=0"), ("train_surrogate", "network=case34bw"),
    ("train_surrogate", "surrogate=pinn"), ("train_pinn", "network=case34bw"),
    ("train_pinn", "pinn_preset.power_balance.max_steps=-1"), ("train_pinn", "pinn_preset=smoke"),
    ("reproduce", "preset.experiments=[nope]"), ("evaluate", "network=case34bw policy=do_nothing"),
    ("evaluate", "policy=nope"),
])
def test_user_errors_come_before_torch(recipe, args, tmp_path):
    """Issue 24: a config or network-name mistake is refused before torch, numba or tensordict is imported (they
    cost 4-10 s of a user's wait), in every recipe; counted in imported modules, not in seconds."""
    env = {**os.environ, "ANM_TORCHRL_HOME": str(tmp_path / "home"), "HYDRA_FULL_ERROR": "0"}
    out = subprocess.run([sys.executable, "-c", LIGHT, str(ROOT / "recipes" / f"{recipe}.py"), *args.split()],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120, env=env)
    assert f"{recipe}.py: " in out.stderr, out.stderr
    assert "heavy modules imported: []" in out.stdout, (out.stdout, out.stderr[-2000:])
    assert "per-network defaults" not in out.stderr  # the error is the only line (the defaults: after the checks)


def test_a_given_surrogate_of_another_network_is_one_line(tmp_path):
    """Bug: ``ppo.py network=case33bw surrogate=pinn surrogate.path=<ANM6-Easy's PINN>`` (or an xgb folder, or
    shac.py model=pinn) stopped with a traceback from inside the training; now one line before the run."""
    import torch

    from anm_torchrl.networks import simulator
    from anm_torchrl.surrogates.pinn import cache
    from anm_torchrl.surrogates.pinn.presets import preset

    torch.set_num_threads(1)
    cache.train_and_save(preset("smoke"), simulator("anm6_easy"), path=tmp_path / "anm6_pinn" / "pinn.safetensors",
                         overwrite_cache=True, jobs=1)
    env = {**os.environ, "ANM_TORCHRL_HOME": str(tmp_path / "home"), "HYDRA_FULL_ERROR": "0", "OMP_NUM_THREADS": "1"}
    for recipe, extra in (("ppo", ["surrogate=pinn"]), ("shac", ["model=pinn", "surrogate=pinn"])):
        out = subprocess.run([sys.executable, str(ROOT / "recipes" / f"{recipe}.py"), "network=case33bw", *extra,
                              "surrogate.path=anm6_pinn"], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                             env=env)
        assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr[-2000:]
        last = out.stderr.strip().splitlines()[-1]
        assert last.startswith(f"{recipe}.py: ") and "was trained on network" in last, last
        assert not (tmp_path / "outputs").exists()
