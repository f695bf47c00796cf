"""anm_torchrl: gym-anm's ANM6-Easy as a batched TorchRL environment, its surrogates and PPO recipes."""

__version__ = "0.1.0"

import anm_torchrl.gym  # noqa: E402,F401  registers the gymnasium ids "anm_torchrl/<Name>-v0"


def make_env(*args, **kwargs):
    """See :func:`anm_torchrl.training.factory.make_env`."""
    from anm_torchrl.training.factory import make_env as _make_env

    return _make_env(*args, **kwargs)
