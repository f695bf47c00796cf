"""A user's pandapower net through the importer: what gym-anm cannot model is refused by name, and what it can
(isolated buses, antiparallel lines) converts; network files that are not what they claim are refused by name.
Each case is a review's reproduction that failed before (a raw IndexError / TypeError, or a net silently
mis-modelled)."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

pp = pytest.importorskip("pandapower")

from anm_torchrl.networks import pandapower_import as ppi  # noqa: E402


def _feeder():
    """ext_grid - line - bus 1 (a load) - line - bus 2 (a PV sgen), 20 kV."""
    net = pp.create_empty_network(sn_mva=1)
    b = [pp.create_bus(net, 20.0) for _ in range(3)]
    pp.create_ext_grid(net, b[0])
    pp.create_line_from_parameters(net, b[0], b[1], 3.0, 0.2, 0.4, 200, 0.4)
    pp.create_line_from_parameters(net, b[1], b[2], 3.0, 0.2, 0.4, 200, 0.4)
    pp.create_load(net, b[1], p_mw=1.0, q_mvar=0.2)
    pp.create_sgen(net, b[2], p_mw=0.5, type="PV")
    return net, b


def _convert(net):
    prepared = ppi.prepare(net)
    return ppi.convert(prepared, np.array([row.p_mw for _, row in prepared.load[prepared.load.in_service].iterrows()]))


def test_an_isolated_bus_is_dropped():
    net, _ = _feeder()
    pp.create_bus(net, 20.0)  # no branch: pandapower 3 gives it a lookup index past its ppc table (an IndexError)
    res = _convert(net)
    assert np.asarray(res.network["bus"]).shape[0] == 3


def test_antiparallel_plain_lines_merge_as_parallel_ones():
    net, b = _feeder()
    pp.create_line_from_parameters(net, b[2], b[1], 3.0, 0.2, 0.4, 200, 0.4)  # bus 2 -> 1, beside 1 -> 2
    branch = np.asarray(_convert(net).network["branch"])
    assert branch.shape[0] == 2  # merged: half the impedance of one line
    one = np.asarray(_convert(_feeder()[0]).network["branch"])
    np.testing.assert_allclose(branch[1, 2:4], one[1, 2:4] / 2, rtol=1e-12)


@pytest.mark.parametrize("element, message", [
    ("gen", r"gens \[0\] control their bus voltage \(PV buses\).*replace_gen_by_sgen"),
    ("reactive_load", r"loads \[1\] have p_mw 0 and q_mvar not; a gym-anm load's Q follows its P"),
    ("nothing", "the pandapower net has no load, generator or storage unit besides its ext_grid"),
    # every problem at once, by pandapower index, with what to do (one round trip, not one per problem)
    ("several", r"cannot represent: shunt \[0\] \(gym-anm has no model for it\); gens \[0\] control.*; sgens "
                r"\[1\] have p_mw < 0.*; 2 in-service ext_grids.*split the net.*set in_service=False"),
    ("no_slack", r"0 in-service ext_grids; gym-anm has exactly one slack bus: add one"),
    # gym-anm counts the slack device's P as the whole bus-0 injection: a load there would count nowhere
    ("at_slack", r"elements on the ext_grid's bus .*\(load \[1\]\).*energy loss still counts it"),
    # named in the same message as the other problems (was: a second round, after the user fixed the first)
    ("at_slack_and_gen", r"gens \[0\] control.*; pandapower elements on the ext_grid's bus or a bus fused with it by "
                         r"a closed bus-bus switch \(load \[1\]; sgen \[1\]\)"),
    # an island (was: "pandapower's ppc has 2 branches, expected 3 in service")
    ("island", r"buses \[3, 4\] are not supplied from the ext_grid .* in-service lines \[2\], loads \[1\]"),
    # an out-of-service bus that still carries an in-service load (was: 'load_peak has 2 entries, expected 1')
    ("oos_bus", r"buses \[2\] are not supplied from the ext_grid .* in-service lines \[1\], sgens \[0\]"),
    # named by pandapower's buses (were gym-anm's ids and raw arrays), with what to do
    ("parallel_taps", r"parallel branches between pandapower buses 2 and 3 differ in .* same tap position and shift"),
])
def test_what_gym_anm_cannot_model_is_refused(element, message):
    net, b = _feeder()
    if element == "gen":  # it was converted into a P/Q generator, its voltage set-point dropped (2.7e-2 p.u.)
        pp.create_gen(net, b[2], p_mw=1.0, vm_pu=1.02, sn_mva=2.0)
    elif element == "reactive_load":  # its Q was dropped (Q/P = 0)
        pp.create_load(net, b[1], p_mw=0.0, q_mvar=-1.5)
    elif element == "several":
        pp.create_shunt(net, b[1], q_mvar=0.1)
        pp.create_gen(net, b[2], p_mw=1.0, vm_pu=1.02, sn_mva=2.0)
        pp.create_sgen(net, b[2], p_mw=-0.5, type="PV")
        pp.create_ext_grid(net, b[2])
    elif element == "no_slack":  # was: a 28-line traceback from pandapower's to_ppc
        net.ext_grid["in_service"] = False
    elif element == "at_slack":  # was: imported, do-nothing returns positive (a negative energy loss)
        pp.create_load(net, b[0], p_mw=0.5, q_mvar=0.1)
    elif element == "at_slack_and_gen":  # the sgen on a bus fused with the ext_grid's by a closed bus-bus switch
        pp.create_gen(net, b[2], p_mw=1.0, vm_pu=1.02, sn_mva=2.0)
        pp.create_load(net, b[0], p_mw=0.5, q_mvar=0.1)
        fused = pp.create_bus(net, 20.0)
        pp.create_switch(net, b[0], fused, et="b", closed=True)
        pp.create_sgen(net, fused, p_mw=0.2, type="PV")
    elif element == "parallel_taps":  # two 20/0.4 kV units side by side, one at another tap position
        lv = pp.create_bus(net, 0.4)
        for tap in (0, 1):
            pp.create_transformer(net, b[2], lv, "0.4 MVA 20/0.4 kV", tap_pos=tap)
    elif element == "oos_bus":
        net.bus.loc[b[2], "in_service"] = False
    elif element == "island":
        i1, i2 = pp.create_bus(net, 20.0), pp.create_bus(net, 20.0)
        pp.create_line_from_parameters(net, i1, i2, 1.0, 0.2, 0.4, 200, 0.4)
        pp.create_load(net, i2, p_mw=0.3, q_mvar=0.1)
    else:
        net.load.drop(net.load.index, inplace=True)
        net.sgen.drop(net.sgen.index, inplace=True)
    with pytest.raises(ValueError, match=message):
        _convert(net)


def test_a_symmetric_series_impedance_is_a_branch():
    """pandapower's ``impedance`` element without shunt terms and equal both ways is a plain gym-anm branch (was
    refused): the converted net's power flow lands on pandapower's; an asymmetric one is refused by index."""
    net, b = _feeder()
    bus = pp.create_bus(net, 20.0)
    pp.create_impedance(net, b[2], bus, 0.01, 0.02, sn_mva=10)
    pp.create_load(net, bus, p_mw=0.2, q_mvar=0.05)
    from anm_torchrl.networks import pf_check

    prepared = ppi.prepare(net)
    loads = np.array([r.p_mw for _, r in prepared.load.iterrows()])
    res = ppi.convert(prepared, loads)
    p, q = pf_check.do_nothing_injections(res.network, -loads, np.array([0.5]))
    pf_check.set_pandapower_point(prepared, res, p, q)
    pf_check.run_pandapower(prepared)
    vm, ok = pf_check.gym_anm_vm(res.network, p, q)
    assert ok and np.abs(pf_check.compare_vm(prepared, res, vm)).max() < 1e-9
    assert np.asarray(res.network["branch"]).shape[0] == 3
    net.impedance.loc[0, "xtf_pu"] = 0.03
    with pytest.raises(ValueError, match=r"impedance \[0\] \(asymmetric or with shunt terms"):
        ppi.prepare(net)


def test_a_three_winding_transformer_converts_through_its_star_point():
    """A 110/20/10 kV trafo3w (tap on hv, a 150 degree shift on lv, no-load losses) below an ext_grid at 1.02 p.u.
    (was: refused as 'no model'): three branches through a star-point bus without voltage limits, rated per winding;
    gym-anm's power flow lands on pandapower's (no-load losses removed in both, as prepare logs) within 1e-9 p.u.;
    a winding whose star-equivalent R is negative is named; out of service, it is left out (and the buses behind
    it with it are named as unsupplied)."""
    from anm_torchrl.networks import pf_check

    net = pp.create_empty_network(sn_mva=1)
    hv, mv, lv, mv2 = (pp.create_bus(net, v) for v in (110.0, 20.0, 10.0, 20.0))
    pp.create_ext_grid(net, hv, vm_pu=1.02)
    pp.create_transformer3w(net, hv, mv, lv, "63/25/38 MVA 110/20/10 kV", tap_pos=2)
    net.trafo3w["shift_lv_degree"] = 150.0
    pp.create_line_from_parameters(net, mv, mv2, 3.0, 0.2, 0.4, 200, 0.4)
    pp.create_load(net, mv2, p_mw=8.0, q_mvar=2.0)
    pp.create_load(net, lv, p_mw=5.0, q_mvar=1.0)
    pp.create_sgen(net, mv2, p_mw=3.0, type="PV")
    prepared = ppi.prepare(net)
    loads = np.array([r.p_mw for _, r in prepared.load.iterrows()])
    res = ppi.convert(prepared, loads)
    bus, branch = np.asarray(res.network["bus"]), np.asarray(res.network["branch"])
    star = 4  # pandapower's buses 0-3 keep their order, the star point comes last
    assert bus.shape[0] == 5 and (bus[star, 3], bus[star, 4], bus[star, 2]) == (ppi.STAR_POINT_VMAX, 0.0, 110.0)
    windings = {tuple(sorted(r[:2].astype(int))): r[5] for r in branch if star in r[:2]}
    assert windings == {(0, star): 63.0, (1, star): 25.0, (2, star): 38.0}
    p, q = pf_check.do_nothing_injections(res.network, -loads, np.array([1.5]))
    pf_check.set_pandapower_point(prepared, res, p, q)
    pf_check.run_pandapower(prepared)
    vm, ok = pf_check.gym_anm_vm(res.network, p, q)
    assert ok and np.abs(pf_check.compare_vm(prepared, res, vm)).max() < 1e-9
    # its star equivalent can have R < 0 on one winding (example_multivoltage's does): named, not gym-anm's traceback
    bad = copy.deepcopy(net)
    bad.trafo3w["vkr_lv_percent"] = 1.5
    with pytest.raises(ValueError, match=r"between pandapower buses \(the star point of trafo3w 0\) and 1 has R = -"):
        ppi.convert(ppi.prepare(bad), loads)
    net.trafo3w["in_service"] = False
    with pytest.raises(ValueError, match=r"buses \[1, 2, 3\] are not supplied from the ext_grid"):
        ppi.prepare(net)


def test_an_open_switch_at_one_winding_opens_that_winding_alone():
    """An open switch at a trafo3w's lv winding (found by review: the whole trafo3w was taken out of service, so a
    10 MW wind sgen on its mv side was dropped silently, or a load behind it refused): the other two windings still
    carry power, as in pandapower (pd2ppc's bus at the open end is left out: nothing is attached there); the sgen is
    kept and the power flow lands on pandapower's within 1e-9 p.u. A bare lv bus behind the open winding is not named
    as unsupplied."""
    from anm_torchrl.networks import pf_check

    for fed in (True, False):  # lv also fed by a two-winding transformer, or bare
        net = pp.create_empty_network(sn_mva=1)
        hv, mv, lv, lv2 = (pp.create_bus(net, v) for v in (110.0, 20.0, 10.0, 10.0))
        pp.create_ext_grid(net, hv, vm_pu=1.02)
        t = pp.create_transformer3w(net, hv, mv, lv, "63/25/38 MVA 110/20/10 kV", tap_pos=2)
        if fed:
            pp.create_transformer(net, hv, lv, "25 MVA 110/10 kV")
            pp.create_line_from_parameters(net, lv, lv2, 1.0, 0.2, 0.4, 200, 0.4)
            pp.create_load(net, lv2, p_mw=6.0, q_mvar=1.0)
        else:
            pp.create_load(net, mv, p_mw=6.0, q_mvar=1.0)
        pp.create_sgen(net, mv, p_mw=10.0, type="wind")
        pp.create_switch(net, lv, t, et="t3", closed=False)
        prepared = ppi.prepare(net)
        loads = np.array([6.0])
        res = ppi.convert(prepared, loads)
        assert res.gen_elements == [("sgen", 0, True)] and prepared.trafo3w.in_service.all()
        p, q = pf_check.do_nothing_injections(res.network, -loads, np.array([10.0]))
        pf_check.set_pandapower_point(prepared, res, p, q)
        pf_check.run_pandapower(prepared)
        vm, ok = pf_check.gym_anm_vm(res.network, p, q)
        assert ok and np.abs(pf_check.compare_vm(prepared, res, vm)).max() < 1e-9


def test_sgens_without_rating_are_left_out(caplog):
    """An sgen with p_mw x scaling = 0 and sn_mva 0 (56 of SimBench 1-HV-urban--0-sw's 98 renewables) can never
    inject: it is left out with a warning (it was imported with a single-value action range, on which the PINN, the
    main job's surrogate, refuses to train); one with sn_mva > 0 and p_mw 0 is kept."""
    import logging

    net, b = _feeder()
    pp.create_sgen(net, b[2], p_mw=0.0, sn_mva=0.0, type="PV")
    pp.create_sgen(net, b[1], p_mw=0.0, sn_mva=0.3, type="PV")
    with caplog.at_level(logging.WARNING, logger=ppi.__name__):
        res = _convert(net)
    assert [i for _, i, _ in res.gen_elements] == [0, 2]
    assert "sgens [1] have no rating" in caplog.text


def test_a_bus_switch_with_impedance_does_not_fuse_buses():
    """A closed bus-bus switch with z_ohm > 0 is an impedance in pandapower, not a fusion (found by review: a load
    behind one was refused as 'on the ext_grid's bus'; what gym-anm cannot model there is the switch itself)."""
    net, b = _feeder()
    behind = pp.create_bus(net, 20.0)
    pp.create_switch(net, b[0], behind, et="b", closed=True, z_ohm=0.5)
    pp.create_load(net, behind, p_mw=0.2, q_mvar=0.05)
    assert ppi._slack_bus_devices(net) == {"load": [], "sgen": []}
    net.switch["z_ohm"] = 0.0
    assert ppi._slack_bus_devices(net) == {"load": [1], "sgen": []}


def test_out_of_service_elements_of_unmodelled_kinds_are_left_out():
    """An impedance (or shunt, trafo3w, ...) that is out of service has nothing to represent: the net converts as
    without it (was: refused as 'not supported')."""
    net, b = _feeder()
    pp.create_impedance(net, b[1], b[2], 0.01, 0.02, sn_mva=10, in_service=False)
    pp.create_shunt(net, b[1], q_mvar=0.1, in_service=False)
    np.testing.assert_array_equal(np.asarray(_convert(net).network["branch"]),
                                  np.asarray(_convert(_feeder()[0]).network["branch"]))


def test_network_files_that_are_not_what_they_claim_are_refused(tmp_path):
    from anm_torchrl.networks import get_network, save_network
    from anm_torchrl.networks.validation import check_reward_args

    case = get_network("case33bw")
    good = save_network(tmp_path / "good.npz", case.network, case.load_p, case.gen_p_max)
    with np.load(good, allow_pickle=False) as z:
        entries = {k: z[k] for k in z.files}
    np.save(tmp_path / "plain.npy", np.zeros(3))
    (tmp_path / "plain.npy").rename(tmp_path / "plain.npz")  # a raw TypeError before
    np.savez(tmp_path / "complex.npz", **{**entries, "branch": entries["branch"] + 7j})  # its imaginary part dropped
    np.savez(tmp_path / "version.npz", **{**entries, "format_version": np.float64(1.7)})  # read as 1
    meta = json.loads(str(entries["meta"]))
    meta["env"]["costs_clipping"] = 5
    np.savez(tmp_path / "clip.npz", **{**entries, "meta": np.array(json.dumps(meta))})  # a raw TypeError before
    for name, message in [("plain", "not an .npz archive"), ("complex", r"branch \(complex128\) must hold real"),
                          ("version", "unreadable format_version entry"), ("clip", "costs_clipping must be")]:
        with pytest.raises(ValueError, match=rf"{name}.npz.*{message}"):
            get_network(str(tmp_path / f"{name}.npz"))
    with pytest.raises(ValueError, match="costs_clipping must be"):
        check_reward_args(0.25, 0.995, 100, 5)


def test_what_the_conversion_leaves_out_is_said(caplog):
    """A transformer's no-load losses (pfe_kw) have no gym-anm model: the conversion says how many kW of the
    pandapower net's losses the env will not count (was: only in the module docstring)."""
    import logging

    net, b = _feeder()
    lv = pp.create_bus(net, 0.4)
    pp.create_transformer(net, b[2], lv, "0.4 MVA 20/0.4 kV")
    pp.create_load(net, lv, p_mw=0.1, q_mvar=0.02)
    with caplog.at_level(logging.WARNING, logger="anm_torchrl.networks.pandapower_import"):
        ppi.prepare(net)
    pfe = float(net.trafo.pfe_kw.sum())
    assert pfe > 0 and f"transformer no-load losses, {pfe:.3g} kW in all" in caplog.text
