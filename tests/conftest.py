"""Test-session set-up: single-threaded torch and a private artifact folder (no cached models leak in)."""

import os
import tempfile

import torch

torch.set_num_threads(1)
os.environ["ANM_TORCHRL_HOME"] = tempfile.mkdtemp(prefix="anm_torchrl_test_home_")
