"""The network identity keys (:mod:`anm_torchrl.grid.identity`) keep their values: committed records, caches and
dataset manifests name them. The expected values were computed by the functions these replaced (commit 725f3f9:
``GridSimulator.content_key``, ``data.storage.network_key`` / ``simulator_fingerprint``,
``networks.registry.content_hash``) on every registered network."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from anm_torchrl.grid import identity
from anm_torchrl.networks import get_network, list_networks, simulator

torch.set_num_threads(1)

EXPECTED = {
    "anm6_easy": ("75059cd710548aa317ba34efd1e3bd7c97e71a7e35ba1f75cf2687ef372649a6", "fbfad07500f1aacf",
                  "fd5c3e1a0470df0d", "54b27910b37f05ee05e72f594ba2d363c82fff9dd37f0202ae02fb162450ea79"),
    # case33bw re-made on 2026-12-03 (MAPDN's PV placement and voltage band): new case, new keys
    "case33bw": ("0089e35fd088a15d39c1f0f944a5582a36aab415bd35bf1948b76063e7e96ddf", "d79fb346ee77ea3e",
                 "0e5b431d89d6cefd", "f5e56812316d3b76ab68f055a290076d3903a73271cbf1aa761412c4035c2642"),
    "cigre_mv": ("494bbdff3c4340725d969268504f0098c15c2c739f6d6271dd76b5ced56798f2", "855b90c1a928f9eb",
                 "a652cbf0563fd5be", "a37842503fa0067e046fb1406a3c1e93348ce36a9f5f1ac1615cd2fcbb34d1b2"),
    "simbench_mv_semiurb": ("6e3330288764e48acf41430e906f05f1de58da4ed07ab9c2ffbde7b3be6f93c0", "69a5b990abe5870f",
                            "540e30b843de8962", "d0cbc853ac2332005818c1e1aabc2c68f713faa6edc31dc2da7d8a93e100e8df"),
}


def test_every_registered_network_is_pinned():
    assert sorted(EXPECTED) == sorted(list_networks())


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_keys_keep_their_values(name):
    sim, case = simulator(name), get_network(name)
    got = (identity.transition_key(sim), identity.network_key(sim), identity.simulator_fingerprint(sim),
           case.content_hash)
    assert got == EXPECTED[name]
    constants = (case.delta_t, case.gamma, case.lamb, tuple(case.costs_clipping))
    assert identity.case_key(case.network, case.load_p, case.gen_p_max, constants) == EXPECTED[name][3]


def test_keys_see_what_they_document():
    """network_key ignores the profiles (a surrogate runs on scaled ones); transition_key and the fingerprint
    do not; every key sees a change of the tables."""
    case = get_network("anm6_easy")
    base = simulator(case)
    scaled = simulator(case, load_p=case.load_p * 0.5)
    assert identity.network_key(scaled) == identity.network_key(base)
    assert identity.transition_key(scaled) != identity.transition_key(base)
    assert identity.simulator_fingerprint(scaled) != identity.simulator_fingerprint(base)
    net = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in case.network.items()}
    net["branch"][1, 5] = 20.0  # a line rating
    other = simulator(net, case.load_p, case.gen_p_max, delta_t=case.delta_t, gamma=case.gamma, lamb=case.lamb,
                      costs_clipping=case.costs_clipping)
    for key in (identity.transition_key, identity.network_key, identity.simulator_fingerprint):
        assert key(other) != key(base), key.__name__
