"""Any SimBench grid or a user's pandapower net as a network file (``python -m anm_torchrl.cli.import_network``):
written only when gym-anm's power flow lands on pandapower's, loadable by every recipe, and the storage units of
SimBench's scenarios (which charge or discharge only) convert instead of failing gym-anm's checks."""

from __future__ import annotations

import logging

import numpy as np
import pytest

pp = pytest.importorskip("pandapower")
pytest.importorskip("simbench")

from anm_torchrl.cli import import_network  # noqa: E402
from anm_torchrl.networks import pandapower_import as ppi  # noqa: E402
from anm_torchrl.networks.user import load_network_file  # noqa: E402
from tests.test_pandapower_import import _feeder  # noqa: E402


def _feeder_json(tmp_path):
    """test_pandapower_import's feeder (a load at bus 1, a PV sgen at bus 2) and a battery at bus 2, as JSON."""
    net, b = _feeder()
    pp.create_storage(net, b[2], p_mw=0.0, max_e_mwh=1.0, min_p_mw=-0.25, max_p_mw=0.25)
    path = tmp_path / "net.json"
    pp.to_json(net, str(path))
    return path


def _lv_net():
    """An LV feeder: ext_grid - line - bus 1 with a 20 kW load (1 MVA base)."""
    net = pp.create_empty_network(sn_mva=1)
    b = [pp.create_bus(net, 0.4) for _ in range(2)]
    pp.create_ext_grid(net, b[0])
    pp.create_line_from_parameters(net, b[0], b[1], 0.1, 0.2, 0.1, 100, 0.3)
    pp.create_load(net, b[1], p_mw=0.02, q_mvar=0.005)
    return net, b


def test_pandapower_net_with_profiles_becomes_a_network_file(tmp_path, capsys):
    net = _feeder_json(tmp_path)
    t = np.arange(8)
    (tmp_path / "loads.csv").write_text("0\n" + "\n".join(f"{0.5 + 0.05 * i}" for i in t))
    (tmp_path / "pv.csv").write_text("0\n" + "\n".join(f"{0.06 * i}" for i in t))
    out = import_network.main(["--pandapower", str(net), "--loads", str(tmp_path / "loads.csv"), "--sgens",
                               str(tmp_path / "pv.csv"), "--out", str(tmp_path / "mine.npz"), "--check-rows", "8"])
    assert out["devices"] == {"load": 1, "classical generator": 0, "renewable": 1, "storage unit": 1}
    assert out["rows"] == 8 and out["vm_max_diff"] < 1e-9  # the same equations solved to round-off
    case = load_network_file(tmp_path / "mine.npz")
    np.testing.assert_allclose(case.load_p[:, 0], -(0.5 + 0.05 * t))  # gym-anm counts a load's P negative
    np.testing.assert_allclose(case.gen_p_max[:, 0], 0.06 * t)
    assert "net.json" in case.source and "train on it: python recipes/ppo.py network=" in capsys.readouterr().out
    # the file is a user network every env builds on
    from anm_torchrl import make_env

    env = make_env("none", network=str(tmp_path / "mine.npz"), num_envs=2)
    td = env.rollout(3)
    assert td["next", "reward"].isfinite().all() and not td["next", "terminated"].any()


def test_refusals_name_what_is_wrong(tmp_path):
    net = _feeder_json(tmp_path)
    (tmp_path / "taken.npz").write_bytes(b"a user's file")
    with pytest.raises(FileExistsError, match="exists"):
        import_network.main(["--pandapower", str(net), "--out", str(tmp_path / "taken.npz")])
    assert (tmp_path / "taken.npz").read_bytes() == b"a user's file"  # nothing lost
    with pytest.raises(ValueError, match="ends with .npz"):
        import_network.main(["--pandapower", str(net), "--out", str(tmp_path / "x.csv")])
    (tmp_path / "bad.csv").write_text("7\n0.5\n")  # no load 7 in the net
    with pytest.raises(ValueError, match=r"the load profile has columns \[7\] that are no load of net.json"):
        import_network.main(["--pandapower", str(net), "--loads", str(tmp_path / "bad.csv"), "--out",
                             str(tmp_path / "y.npz")])
    net_obj = pp.from_json(str(net))
    pp.create_load(net_obj, 1, p_mw=0.1, in_service=True)
    pp.to_json(net_obj, str(tmp_path / "net2.json"))
    (tmp_path / "only1.csv").write_text("1\n0.5\n")  # load 0 has no column
    with pytest.raises(ValueError, match=r"no column for pandapower loads \[0\]"):
        import_network.main(["--pandapower", str(tmp_path / "net2.json"), "--loads", str(tmp_path / "only1.csv"),
                             "--out", str(tmp_path / "y.npz")])
    (tmp_path / "nan.csv").write_text("0\nnan\n")
    with pytest.raises(ValueError, match="finite MW"):
        import_network.main(["--pandapower", str(net), "--loads", str(tmp_path / "nan.csv"), "--out",
                             str(tmp_path / "y.npz")])
    with pytest.raises(ValueError, match="not a pandapower net"):
        import_network.main(["--pandapower", str(tmp_path / "taken.npz"), "--out", str(tmp_path / "y.npz")])
    with pytest.raises(SystemExit):  # argparse: a SimBench option with a pandapower net
        import_network.main(["--pandapower", str(net), "--days", "2", "--out", str(tmp_path / "y.npz")])
    assert not (tmp_path / "y.npz").exists()


def test_one_way_storage_converts_inside_its_range(caplog):
    """SimBench's home batteries have max_p_mw 0 (discharge only): the inverter polygon's charging corner (-0.8 S)
    fell below PMIN = 0 and gym-anm refused the device table ("P- outside [PMIN, PMAX]")."""
    net, b = _lv_net()
    pp.create_storage(net, b[1], p_mw=-0.05, max_e_mwh=0.1, min_p_mw=-0.05, max_p_mw=0.0, name="home battery")
    import pandas as pd

    with caplog.at_level(logging.WARNING):
        _, res, load_p, gen_p_max = ppi.from_pandapower(net, pd.DataFrame({0: [0.02, 0.03]}), pd.DataFrame())
    assert "1 pandapower storage units can only discharge" in caplog.text
    dev = res.network["device"][-1]
    pmax, pmin, p_plus, p_minus = dev[4], dev[5], dev[8], dev[9]
    assert (pmax, pmin) == (0.05, 0.0) and pmin <= p_minus <= p_plus <= pmax
    from anm_torchrl.networks.user import checked_case

    checked_case("one_way", res.network, load_p, gen_p_max)  # gym-anm's checks pass
    # opt-in: the same unit two-way, its P range mirrored, the corners at +-0.8 S, as every two-way unit's
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _, res, load_p, gen_p_max = ppi.from_pandapower(net, pd.DataFrame({0: [0.02, 0.03]}), pd.DataFrame(),
                                                        ppi.ImportDefaults(storage_two_way=True))
    assert "can only discharge" in caplog.text and "made two-way" in caplog.text
    dev = res.network["device"][-1]
    assert (dev[4], dev[5]) == (0.05, -0.05) and dev[8] == pytest.approx(0.04) and dev[9] == pytest.approx(-0.04)
    checked_case("two_way", res.network, load_p, gen_p_max)


def test_two_way_storage_option_is_recorded_in_the_file(tmp_path):
    """``--two-way-storage`` reaches the conversion (a one-way battery gets PMIN = -PMAX) and the file's source."""
    net, b = _lv_net()
    pp.create_storage(net, b[1], p_mw=0.0, max_e_mwh=0.1, min_p_mw=-0.05, max_p_mw=0.0)
    pp.to_json(net, str(tmp_path / "net.json"))
    for flag, pmin in (([], 0.0), (["--two-way-storage"], -0.05)):
        out = tmp_path / f"g{len(flag)}.npz"
        import_network.main(["--pandapower", str(tmp_path / "net.json"), "--rows", "4", "--out", str(out), *flag])
        case = load_network_file(out)
        assert case.network["device"][-1, 5] == pmin
        assert ("made two-way" in case.source) is bool(flag)


@pytest.mark.slow
def test_simbench_grid_imports_and_trains(tmp_path):
    """A SimBench grid nobody registered (15 buses, 13 loads, 4 PV units), one day of its own profiles."""
    out = import_network.main(["--simbench", "1-LV-rural1--0-sw", "--days", "1", "--out", str(tmp_path / "r1.npz")])
    assert out["buses"] == 15 and out["devices"]["renewable"] == 4 and out["rows"] == 96
    assert out["vm_max_diff"] < 1e-9
    from anm_torchrl import make_env

    td = make_env("none", network=str(tmp_path / "r1.npz"), num_envs=4).rollout(96)
    assert td["next", "reward"].isfinite().all() and not td["next", "terminated"].any()


def test_own_reactive_limits_replace_the_defaults():
    """An sgen's or a battery's own min/max_q_mvar were ignored (the inverter polygon's +-0.6 S taken instead)."""
    net, b = _feeder()
    net.sgen.loc[0, ["max_q_mvar", "min_q_mvar"]] = 0.1, -0.05
    pp.create_storage(net, b[2], p_mw=0.0, max_e_mwh=1.0, min_p_mw=-0.25, max_p_mw=0.25, max_q_mvar=0.2,
                      min_q_mvar=0.05)
    import pandas as pd

    _, res, load_p, gen_p_max = ppi.from_pandapower(net, pd.DataFrame({0: [1.0]}), pd.DataFrame({0: [0.4]}))
    pv, battery = res.network["device"][2], res.network["device"][3]
    assert (pv[6], pv[7], pv[10], pv[11]) == (0.1, -0.05, 0.0, 0.0)  # QMAX, QMIN, Q+, Q-
    assert (battery[6], battery[7], battery[10], battery[11]) == (0.2, 0.05, 0.05, 0.05)  # 0 outside: nearest
    from anm_torchrl.networks.user import checked_case

    checked_case("own_q", res.network, load_p, gen_p_max)
    net.sgen.loc[0, "min_q_mvar"] = 0.3
    with pytest.raises(ValueError, match=r"sgen 0: min_q_mvar 0.3 > max_q_mvar 0.1"):
        ppi.from_pandapower(net, pd.DataFrame({0: [1.0]}), pd.DataFrame({0: [0.4]}))


def test_a_net_without_controllable_device_is_written_and_said_so(tmp_path, capsys):
    """A loads-only net (9 of pandapower's 12 stock nets that import) is written (do-nothing can be evaluated on it)
    but the command does not send the user to a training recipe that refuses it."""
    def imported(name):
        pp.to_json(net, str(tmp_path / f"{name}.json"))
        out = import_network.main(["--pandapower", str(tmp_path / f"{name}.json"), "--rows", "4",
                                   "--out", str(tmp_path / f"{name}.npz")])
        printed = capsys.readouterr().out
        assert "train on it" not in printed and "recipes/evaluate.py policy=do_nothing" in printed
        return out, printed

    net, _ = _feeder()
    net.sgen.drop(net.sgen.index, inplace=True)
    out, printed = imported("loads_only")
    assert out["devices"]["load"] == 1 and "no controllable device" in printed
    # a storage unit without any P or Q range: a device, but nothing to act on (was: "train on it", which refused)
    pp.create_storage(net, 2, p_mw=0.0, max_e_mwh=1.0, min_p_mw=0.0, max_p_mw=0.0, min_q_mvar=0.0, max_q_mvar=0.0)
    out, printed = imported("flat")
    assert out["devices"]["storage unit"] == 1 and "every controllable device is a single value" in printed


def test_two_way_storage_names_only_the_units_it_changed(tmp_path, caplog):
    """``--two-way-storage`` on a battery that is two-way already changes nothing and the file's source says
    nothing; a unit without any P range (min_p_mw = max_p_mw = 0) is not 'mirrored' (found by review: it was counted
    twice and the source claimed a change)."""
    net, b = _lv_net()
    pp.create_storage(net, b[1], p_mw=0.0, max_e_mwh=0.1, min_p_mw=-0.05, max_p_mw=0.05)
    pp.create_storage(net, b[1], p_mw=0.0, max_e_mwh=0.1, min_p_mw=0.0, max_p_mw=0.0)
    pp.to_json(net, str(tmp_path / "net.json"))
    with caplog.at_level(logging.WARNING):
        import_network.main(["--pandapower", str(tmp_path / "net.json"), "--rows", "4", "--out",
                             str(tmp_path / "g.npz"), "--two-way-storage"])
    assert "made two-way" not in load_network_file(tmp_path / "g.npz").source
    assert "indices [1, 1]" not in caplog.text and "made two-way" not in caplog.text


@pytest.mark.parametrize("tap_pos, shift", [(-1, 0.0), (2, 5.0)])
def test_a_transformer_tapped_towards_the_slack_bus_converts(tmp_path, tap_pos, shift):
    """case118's transformer 67-68 has its tap on the side away from the ext_grid's bus (was refused: gym-anm's tap
    is on a branch's from side and the slack's set-point folds into branches leaving bus 0). It is the same two-port
    drawn from bus 0 (tap 1/τ, z·τ², B/τ²): the file is written only if gym-anm's power flow lands on pandapower's,
    here with the slack at 1.035∠30°."""
    net = pp.create_empty_network(sn_mva=100)
    hv, slack, far = pp.create_bus(net, 161.0), pp.create_bus(net, 138.0), pp.create_bus(net, 161.0)
    pp.create_ext_grid(net, slack, vm_pu=1.035, va_degree=30.0)
    pp.create_transformer_from_parameters(net, hv, slack, sn_mva=9900, vn_hv_kv=161, vn_lv_kv=138, vkr_percent=0.1,
                                          vk_percent=366.3, pfe_kw=0, i0_percent=0, tap_side="hv", tap_neutral=0,
                                          tap_step_percent=6.5, tap_pos=tap_pos, shift_degree=shift,
                                          tap_changer_type="Ratio")
    pp.create_line_from_parameters(net, hv, far, 20.0, 0.05, 0.4, 10, 0.8)
    pp.create_load(net, far, p_mw=60, q_mvar=15)
    pp.create_sgen(net, hv, p_mw=20, type="PV")
    pp.to_json(net, str(tmp_path / "net.json"))
    out = import_network.main(["--pandapower", str(tmp_path / "net.json"), "--rows", "4", "--check-rows", "4",
                               "--out", str(tmp_path / "t.npz")])
    assert out["vm_max_diff"] < 1e-9
    branch = load_network_file(tmp_path / "t.npz").network["branch"]
    (trafo,) = branch[branch[:, 0] == 0]  # drawn from the slack bus, its tap on that side
    assert trafo[1] == 1 and not np.isclose(trafo[6], 1.0)
