"""Tests of the selection rule of diagnose (heldout.verdict): the total held-out error must fall, no joint may get
significantly worse, and the per-joint held-out RMS changes in the report and JSON match a direct 2-fold computation."""
import functools
import re

import numpy as np

from diagnosis import diagnose as D
from diagnosis.effect_model import Model
from diagnosis.effects import Signals, custom
from diagnosis.logs import Log
from dynamics import Robot

ROBOT = Robot.panda()
DT, SECONDS, BLOCK = 1e-3, 6.0, 0.5              # 12 blocks of exactly 500 samples (DiagnoseConfig.block)
NOISE = 0.02                                     # Nm, white torque noise: the Panda's torque resolution
WEIGHTS = np.array([1.0, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5])   # the coupled candidate: torque a * WEIGHTS on all joints


@functools.lru_cache(maxsize=None)
def synthetic(hidden: str) -> Log:
    """A 6 s log of smooth motion whose tau_J is the nominal model (Eq. 1) plus the hidden torque plus white noise:
    'offset1' = 0.3 Nm on joint 1 only; 'viscous' = fv dq on every joint."""
    t = DT * np.arange(int(round(SECONDS / DT)))
    w = 2 * np.pi * np.linspace(0.3, 0.7, 7)
    q0, amp = np.array([0, -0.3, 0, -2.0, 0, 1.9, 0.8]), np.full(7, 0.4)
    q = q0 + amp * np.sin(w * t[:, None])                             # (T, 7)
    dq, ddq = amp * w * np.cos(w * t[:, None]), -amp * w ** 2 * np.sin(w * t[:, None])
    log = Log(t, q, dq, ddq, np.zeros_like(q), None, {"source": f"synthetic {hidden}", "dt": DT})
    tau = Signals(log, ROBOT).inverse_dynamics.copy()
    if hidden == "offset1":
        tau[:, 0] += 0.3
    elif hidden == "viscous":
        tau += np.array([0.6, 0.6, 0.5, 0.5, 0.3, 0.3, 0.2]) * dq
    tau += NOISE * np.random.default_rng(5).normal(size=tau.shape)
    return Log(t, q, dq, ddq, tau, None, log.info)


def coupled():
    """A candidate whose one parameter a adds a * WEIGHTS to all joints: it can fit joint 1 only by adding torque on
    joints 2-7 as well."""
    return custom("coupled", "one torque shared by all joints", lambda s: np.broadcast_to(
        WEIGHTS[None, :, None], (len(s), 7, 1)).copy(), ["a"], ["Nm"])


def direct_rms_change(log: Log, A: np.ndarray) -> np.ndarray:
    """Per joint (n,): held-out RMS with the effect / without it - 1, by 2-fold over interleaved blocks of BLOCK s,
    fitting the effect's parameters p by lstsq on the stacked joints of one fold's blocks (A (T, n, k)) and scoring
    on the other's. The input model (nominal) has no free parameters: without the effect the held-out residual is y."""
    y = log.tau_J - Signals(log, ROBOT).inverse_dynamics              # (T, n)
    fold = (np.floor((log.t - log.t[0]) / BLOCK + 1e-9).astype(int)) % 2
    sse = np.zeros(y.shape[1])
    for f in (0, 1):
        tr, te = fold == f, fold != f
        p = np.linalg.lstsq(A[tr].reshape(-1, A.shape[2]), y[tr].reshape(-1), rcond=None)[0]
        sse += np.sum((y[te] - A[te] @ p) ** 2, axis=0)
    return np.sqrt(sse / np.sum(y ** 2, axis=0)) - 1


def test_effect_that_helps_one_joint_and_hurts_the_others_is_not_selected():
    log = synthetic("offset1")
    d = D.diagnose(Model.nominal(ROBOT), log, candidates=[coupled()])
    r = d.ranking[0]
    assert d.selected == [] and not r["significant"], (d.selected, d.stop)
    assert r["joints"] == [1]                          # it does cut joint 1's error (the per-joint rule alone passes)
    assert r["total_change"] < 0                       # and even the summed error, but ...
    assert r["worse"] == [2, 3, 4, 5, 6, 7], r["rms_change"]   # ... every other joint gets much worse
    assert np.all(np.array(r["rms_change"][1:]) > 1.0)         # its RMS more than doubles there
    assert "worse on joints [2, 3, 4, 5, 6, 7]" in d.stop
    # offered beside the right effect, the right one is selected, and the coupled one never
    d2 = D.diagnose(Model.nominal(ROBOT), log, candidates=[coupled(), "offset"])
    assert d2.selected == ["offset"], d2.selected


def test_helpful_effect_is_selected_and_lowers_every_joint_in_the_json():
    out = D.run(synthetic("viscous"))
    assert out["diagnosis"].selected[:1] == ["viscous"], out["diagnosis"].selected
    top = next(r for r in out["json"]["ranking"] if r["effect"] == "viscous")
    change = np.array(top["rms_change_percent"])
    assert top["significant"] and top["worse_joints"] == [] and change.shape == (7,)
    assert np.all(change < -50), change                   # viscous torque >> noise on every joint
    assert top["total_change_percent"] < -50


def test_reported_per_joint_changes_match_a_direct_two_fold_fit():
    log = synthetic("offset1")
    d = D.diagnose(Model.nominal(ROBOT), log, candidates=[coupled(), "offset"])
    text = D.format_diagnosis(d)
    lines = text.splitlines()
    for name, A in (("coupled", np.broadcast_to(WEIGHTS[None, :, None], (len(log), 7, 1))),
                    ("offset", np.broadcast_to(np.eye(7)[None], (len(log), 7, 7)))):
        want = 100 * direct_rms_change(log, A)
        r = next(r for r in d.ranking if r["effect"] == name)
        np.testing.assert_allclose(100 * r["rms_change"], want, rtol=1e-6, atol=1e-6)
        i = next(i for i, ln in enumerate(lines) if re.match(rf"\s+\d+ {name}\s", ln))
        shown = np.array([float(v) for v in lines[i + 1].split()[-7:]])      # the row under the effect's row
        np.testing.assert_allclose(shown, want, atol=0.051)                   # printed with one decimal
    assert want[0] < -80 and np.all(np.abs(want[1:]) < 1)                     # offset: joint 1 only, the rest noise
