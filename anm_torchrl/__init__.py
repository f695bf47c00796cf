"""anm_torchrl: gym-anm's ANM6-Easy as a batched TorchRL environment, its surrogates and PPO recipes."""
