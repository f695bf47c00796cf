"""docs/GUIDE.md and recipes/README.md say what runs: every Python block of the guide runs on its own in a fresh
interpreter, and every recipe command of both pages (``python recipes/<x>.py key=value ...``) has options the
recipe accepts (composed against its config, nothing run)."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "GUIDE.md"
PAGES = (GUIDE, ROOT / "recipes" / "README.md")


def blocks(page: Path, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", page.read_text(), flags=re.S)


def commands(page: Path) -> list[list[str]]:
    """Recipe command lines of a page's bash blocks (comments stripped, continuation lines joined)."""
    out = []
    for block in blocks(page, "bash"):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split(" # ")[0].strip()
            if line.startswith("python recipes/"):
                out.append(shlex.split(line)[1:])
    return out


GUIDE_BLOCKS = blocks(GUIDE, "python")
COMMANDS = [(page.relative_to(ROOT).as_posix(), argv) for page in PAGES for argv in commands(page)]


def test_pages_have_what_this_file_checks():
    assert len(GUIDE_BLOCKS) >= 4, "the guide's Python blocks were not found"
    scripts = {Path(argv[0]).name for _, argv in COMMANDS}
    assert {"ppo.py", "evaluate.py", "train_pinn.py", "make_dataset.py", "train_surrogate.py",
            "reproduce.py"} <= scripts, scripts


@pytest.mark.parametrize("index", range(len(GUIDE_BLOCKS)))
def test_guide_block_runs_on_its_own(index, tmp_path):
    """A fresh interpreter in an empty folder: the block imports what it uses and needs no earlier block."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", GUIDE_BLOCKS[index]], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, f"GUIDE block {index} failed:\n{GUIDE_BLOCKS[index]}\n{proc.stderr[-3000:]}"
    assert proc.stdout.strip(), "every block prints what it shows"


def first_of_sweeps(overrides: list[str]) -> list[str]:
    """Multirun overrides (``a=1,2``) reduced to their first value, as the first job of the sweep gets them."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    out = []
    for text, ov in zip(overrides, OverridesParser.create().parse_overrides(overrides)):
        out.append(f"{ov.get_key_element()}={next(ov.sweep_string_iterator())}" if ov.is_sweep_override() else text)
    return out


@pytest.mark.parametrize("page, argv", COMMANDS, ids=[f"{p}:{' '.join(a)[:60]}" for p, a in COMMANDS])
def test_documented_command_options_exist(page, argv):
    script = ROOT / argv[0]
    args = [a for a in argv[1:] if a not in ("-m", "--multirun", "--help")]
    if script.name == "evaluate.py":
        import importlib.util

        spec = importlib.util.spec_from_file_location("evaluate_recipe", script)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        module.parse_args([a for a in args if not a.startswith("checkpoint=")] + ["policy=do_nothing"]
                          if not any(a.startswith("policy=") for a in args) else args)
        return
    from hydra import compose, initialize_config_dir

    config_name = re.search(r'config_name="(\w+)"', script.read_text()).group(1)
    with initialize_config_dir(config_dir=str(script.parent / "conf"), version_base="1.3"):
        cfg = compose(config_name=config_name, overrides=first_of_sweeps(args), return_hydra_config=True)
    assert OmegaConf.select(cfg, "hydra.runtime.choices") is not None


RECIPE_GROUPS = {"ppo": {"checkpoint", "collector", "env", "eval", "logger", "loss", "model", "optim", "per_network",
                         "surrogate"},
                 "train_pinn": {"pinn_preset"}, "train_surrogate": {"models", "surrogate", "terminal"},
                 "make_dataset": set(), "reproduce": {"preset"}}


@pytest.mark.parametrize("recipe", sorted(RECIPE_GROUPS))
def test_help_lists_only_the_recipes_groups(recipe):
    """``--help`` shows the groups of the recipe's own defaults list (Hydra's default lists every folder of
    recipes/conf/, other recipes' too), each with its options."""
    from hydra import compose, initialize_config_dir

    from anm_torchrl.training.recipe_help import recipe_groups, register

    register()
    script = ROOT / "recipes" / f"{recipe}.py"
    assert "register_help()" in script.read_text()
    config_name = re.search(r'config_name="(\w+)"', script.read_text()).group(1)
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "conf"), version_base="1.3"):
        cfg = compose(config_name=config_name, return_hydra_config=True)
    template = OmegaConf.to_container(cfg.hydra.help, resolve=False)["template"]
    assert "${recipe_groups:}" in template, "the recipe does not use hydra/help=recipe"
    text = recipe_groups(cfg)
    listed = {line.split(":")[0] for line in text.splitlines() if "(now: " in line}
    assert listed == RECIPE_GROUPS[recipe], text
    if recipe == "ppo":
        assert "surrogate: dnn, dt, gym_anm, lr, none, pinn, rf, xgb (now: none)" in text


def test_run_directory_names_a_network_file_by_its_stem():
    """Bug: train_pinn.py's run directory embedded ``network=`` as given, so a network file's path nested folders
    (``outputs/train_pinn/<date>/<time>_/tmp/x/feeder.npz_default``)."""
    from omegaconf import OmegaConf

    from anm_torchrl.training.recipe_help import register

    register()
    assert OmegaConf.create({"n": "/tmp/x/feeder.npz", "d": "${network_label:${n}}"}).d == "feeder"
    assert OmegaConf.create({"n": "case33bw", "d": "${network_label:${n}}"}).d == "case33bw"
    assert "${network_label:${network}}" in (Path(__file__).parents[1] / "recipes/conf/train_pinn.yaml").read_text()
