"""Saved models and other arms: a fitted model round-trips exactly through JSON and RME uses it; the diagnosis command
line runs on a 6-joint arm given by its MJCF."""
import json

import numpy as np
import pytest

from diagnosis import diagnose as D
from diagnosis.effect_model import Model
from diagnosis.excite import ExciteConfig, multisine
from diagnosis.logs import prepare
from dynamics import Q_READY, Robot
from experiments.episodes import plant_config, record_log, save_log
from rme import RME

ARM6 = """<mujoco model="arm6">
  <option timestep="0.001" gravity="0 0 -9.81"/>
  <worldbody>
    <body name="l1" pos="0 0 0.1"><joint name="j1" axis="0 0 1" range="-3 3"/>
      <inertial pos="0 0 0.1" mass="2.0" diaginertia="0.02 0.02 0.01"/>
      <body name="l2" pos="0 0 0.2"><joint name="j2" axis="0 1 0" range="-2 2"/>
        <inertial pos="0.15 0 0" mass="1.8" diaginertia="0.01 0.03 0.03"/>
        <body name="l3" pos="0.3 0 0"><joint name="j3" axis="0 1 0" range="-2.5 2.5"/>
          <inertial pos="0.12 0 0" mass="1.2" diaginertia="0.005 0.02 0.02"/>
          <body name="l4" pos="0.25 0 0"><joint name="j4" axis="1 0 0" range="-3 3"/>
            <inertial pos="0.05 0 0" mass="0.6" diaginertia="0.002 0.003 0.003"/>
            <body name="l5" pos="0.1 0 0"><joint name="j5" axis="0 1 0" range="-2 2"/>
              <inertial pos="0.04 0 0" mass="0.4" diaginertia="0.001 0.002 0.002"/>
              <body name="l6" pos="0.08 0 0"><joint name="j6" axis="1 0 0" range="-3 3"/>
                <inertial pos="0.03 0 0.01" mass="0.3" diaginertia="0.001 0.001 0.001"/>
                <site name="tip" pos="0.06 0 0"/>
              </body></body></body></body></body></body>
  </worldbody>
  <actuator>
    <motor joint="j1" ctrlrange="-50 50"/><motor joint="j2" ctrlrange="-50 50"/><motor joint="j3" ctrlrange="-30 30"/>
    <motor joint="j4" ctrlrange="-10 10"/><motor joint="j5" ctrlrange="-10 10"/><motor joint="j6" ctrlrange="-5 5"/>
  </actuator>
</mujoco>
"""


@pytest.fixture(scope="module")
def fitted():
    """Sigmoid friction and torque offsets hidden in a simulated Panda log; the model with both fitted."""
    config, _ = plant_config(("sigmoid", "offset"))
    log = prepare(record_log(config, 6.0, np.random.default_rng(3)))
    model = Model.nominal(Robot.panda()).add("sigmoid").add("offset")
    model.fit(log)
    return model, log


@pytest.mark.slow
def test_a_saved_model_round_trips_exactly_and_rme_uses_it(fitted, tmp_path):
    model, log = fitted
    model.save(tmp_path / "model.json")
    loaded = Model.load(tmp_path / "model.json")
    assert loaded.names == model.names and loaded.fixed == model.fixed and loaded.fitted
    for name in model.names:
        np.testing.assert_array_equal(loaded.params[name], model.params[name])
    np.testing.assert_array_equal(loaded.nl["sigmoid"], model.nl["sigmoid"])
    rng = np.random.default_rng(5)
    q, dq = Q_READY + 0.2 * rng.normal(size=(50, 7)), 0.3 * rng.normal(size=(50, 7))
    np.testing.assert_array_equal(loaded.correction(q, dq), model.correction(q, dq))
    assert np.abs(model.correction(q, dq)).max() > 0.05                     # the correction is not trivially zero
    window_q = Q_READY + 0.01 * rng.normal(size=(200, 7))
    tau = Robot.panda().payload_torque(window_q, [0.8, 0.03, 0.0, 0.1]) + 0.02 * rng.normal(size=(200, 7))
    a = RME(correction=model, rng=np.random.default_rng(1)).estimate(window_q, tau, dq=np.zeros((200, 7)))
    b = RME(correction=loaded, rng=np.random.default_rng(1)).estimate(window_q, tau, dq=np.zeros((200, 7)))
    np.testing.assert_array_equal(a.mean, b.mean)
    c = RME(rng=np.random.default_rng(1)).estimate(window_q, tau)
    assert np.abs(c.mean - a.mean).max() > 1e-4                             # the correction does change it


def test_a_model_file_that_is_not_one_is_a_value_error(tmp_path):
    (tmp_path / "bad.json").write_text("{\"format\": \"something else\"}")
    with pytest.raises(ValueError, match="bad.json"):
        Model.load(tmp_path / "bad.json")
    with pytest.raises(ValueError, match="path"):
        Model.load(tmp_path / "absent.json")


@pytest.mark.slow
def test_the_command_line_saves_the_model_it_fits(fitted, tmp_path):
    _, log = fitted
    path = tmp_path / "log.npz"
    np.savez(path, t=log.t, q=log.q, dq=log.dq, tau_J=log.tau_J, tau_ext=log.tau_ext, tau_ext_sign="paper")
    assert D.main([str(path), "--add", "sigmoid", "offset", "--save", str(tmp_path / "m.json")]) == 0
    m = Model.load(tmp_path / "m.json")
    assert m.names == ["gravity", "motion", "sigmoid", "offset"] and m.fitted


@pytest.mark.slow
def test_a_six_joint_arm_runs_through_the_command_line(tmp_path, capsys):
    """A log of a 6-joint arm (its own MJCF) with hidden viscous friction: the command line, given --xml and --ee,
    compares, diagnoses and names viscous friction; without --xml the joint count is refused."""
    xml = tmp_path / "arm6.xml"
    xml.write_text(ARM6)
    arm = Robot.from_xml(str(xml), ee="tip")
    t = 1e-3 * np.arange(12_000)
    q, dq, ddq = multisine(t, ExciteConfig(center=(0.0, 0.3, -0.6, 0.0, 0.4, 0.0), speed=0.8),
                           np.random.default_rng(2))
    fv = np.array([0.4, 0.5, 0.3, 0.1, 0.08, 0.05])                          # Nm s/rad, hidden
    tau_J = arm.inverse_dynamics(q, dq, ddq) + fv * dq + 0.005 * np.random.default_rng(3).normal(size=q.shape)
    save_log(tmp_path / "arm6.npz", {"t": t, "q": q, "dq": dq, "tau_J": tau_J})
    capsys.readouterr()
    assert D.main([str(tmp_path / "arm6.npz"), "--xml", str(xml), "--ee", "tip", "--add", "auto", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["selected"][0] == "viscous"
    np.testing.assert_allclose(out["after"]["params"]["viscous"], fv, rtol=0.05)
    assert D.main([str(tmp_path / "arm6.npz")]) == 2                         # the Panda has 7 joints
    assert "6 joints" in capsys.readouterr().err


def test_a_model_file_is_checked_field_by_field(fitted, tmp_path):
    model, _ = fitted
    model.save(tmp_path / "good.json")
    doc = json.loads((tmp_path / "good.json").read_text())
    assert "xml" not in doc["robot"] and doc["robot"]["name"] == "panda"        # the arm by name, no absolute path

    def edited(change):
        d = json.loads(json.dumps(doc))
        change(d)
        return d
    viscous = {"name": "viscous", "fixed": False, "params": [-50.0] * 7, "nonlinear": None}
    cases = [
        (lambda d: d["effects"].append(viscous), r"effects\[4\]\.params: expected 'viscous' values within \[0, "),
        (lambda d: d["effects"].append(dict(viscous, params=[1e300] * 7)), r"found 1e\+300"),
        (lambda d: d.pop("effects"), r"effects: expected a field 'effects', found none"),
        (lambda d: d.update(effects=[]), r"effects: expected a non-empty list"),
        (lambda d: d["effects"][0].update(params=[1e300]), r"effects\[0\]\.params: .*'gravity'.*found 1e\+300"),
        (lambda d: d["effects"][2].update(nonlinear=[[5.0, 9.0]] * 7), r"effects\[2\]\.nonlinear: .*within"),
        (lambda d: d["effects"][3].update(params=["0.1"] * 7), r"effects\[3\]\.params: expected real numbers"),
        (lambda d: d["effects"].append(dict(doc["effects"][3])), r"effects\[4\]\.name: expected each effect once"),
        (lambda d: d.update(fitted="yes"), r"fitted: expected bool, found 'yes'"),
        (lambda d: d["robot"].update(n=6), r"robot\.n: expected 7 joints like the arm, found 6"),
        (lambda d: d["config"].update(tilt_max=float("nan")), r"config\.tilt_max: expected finite real numbers"),
    ]
    for change, message in cases:
        (tmp_path / "bad.json").write_text(json.dumps(edited(change)))
        with pytest.raises(ValueError, match=message):
            Model.load(tmp_path / "bad.json")
    (tmp_path / "bom.json").write_bytes(b"\xef\xbb\xbf" + (tmp_path / "good.json").read_bytes())
    assert Model.load(tmp_path / "bom.json").names == model.names           # an editor's byte-order mark


def test_fixed_parameters_and_fit_rows_are_checked(fitted):
    _, log = fitted
    for bad, message in (([np.nan] * 7, "finite"), ([-50.0] * 7, "within"), ([1e300] * 7, "within"),
                         ([1j] * 7, "real numbers"), ([0.1] * 6, r"shape \(7,\)")):
        with pytest.raises(ValueError, match=f"fixed: expected .*{message}"):
            Model.nominal(Robot.panda()).add("viscous", fixed=bad)
    with pytest.raises(ValueError, match="rows: expected enough samples to fit 7 parameters .* found 0 rows"):
        Model.nominal(Robot.panda()).add("offset").fit(log, rows=[])


def test_output_folders_are_checked_before_the_work_starts(tmp_path, capsys):
    for flag in ("--save", "--plot"):
        args = [str(tmp_path / "absent.npz"), "--add", "offset", flag, str(tmp_path / "no" / "such" / "f")]
        assert D.main(args) == 2                       # the folder is refused before the (absent) log is read
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"error: {flag}: expected a writable folder") and "\n" not in err, err
