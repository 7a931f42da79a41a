"""What the pipeline (rme.py) is told: RMESettings, the streaming estimator's settings (rme re-exports it), and
faulty, which tau_ext samples are sensor faults."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

import checks
import vi
from detector import MAX_TORQUE, DetectorSettings


@dataclass(frozen=True)
class RMESettings:
    window: int = 200              # samples of the estimation window: 200 ms at 1 kHz (Sec. 4, App. E); at a
                                   #   detection at most detection_window (below)
    reference: int = 30            # samples at the start of the detector's buffer (which checks they precede the
                                   #   change) whose mean tau_ext the window is referred to, extended while the level
                                   #   holds (detector.steady_prefix) (ours: removes the pose-dependent bias)
    rate: float = 1000.0           # Hz, the control loop (Franka's 1 kHz)
    use_network: bool = True       # prior mean from the network (False: zero prior mean, Table 1's ablation)
    asynchronous: bool = True      # ours: compensation starts once the estimate's own wall time has passed, as if
                                   #   the estimate ran beside the loop (False: applied on the detection sample)
    max_mass: float = 3.0          # kg, Panda's rated payload: the compensation never assumes more
    max_com: float = 0.3           # m, |rx|, |ry|, |rz| of a payload a hand can carry (ours); an estimate with its
                                   #   CoM further out is not a payload (a push, a bias change) and is not applied
    min_explained: float = 0.9     # ours: share of the window's torque change a new estimate must explain; a bias
                                   #   change after a large move explains 0.6-0.7, loads 0.97-1.0 (pick-place, basket)
    refine: bool = True            # ours: estimate again once the arm is still after a detection (friction held
                                   #   part of the load while it moved: the first estimate reads light by a few %)
    rest_speed: float = 0.01       # rad/s, every joint slower than this counts as still (dq noise is 1e-3)
    refine_within: float = 2.0     # s after the detection for the arm to be still; from its last 0.5 s on, calm will do
                                   #   (a creeping arm), up to 3 x refine_within (a push kept it moving); then the monitor
    monitor: bool = True           # ours: while the arm is still, check that the compensated estimate explains
                                   #   tau_ext; if it persistently does not, estimate again (see RME.update)
    monitor_threshold: float = 0.3  # Nm, |mean residual - the level last explained| that counts as unexplained (0.1 kg
                                   #   moves the Panda's torques by ~0.5 Nm; the realistic bias drifts < 0.1 Nm at rest)
    monitor_window: int = 300      # samples (300 ms): the arm calm and the residual level steady this long
    monitor_far: float = 2.0       # Nm: at a pose never seen, a level this far from the nearest known one is no
                                   #   sensor bias (a few tenths of a Nm per joint) but a change missed (e.g. in a push)
    monitor_speed: float = 0.02    # rad/s: every joint slower than this counts as calm for the monitor (friction
                                   #   torque then stays below about 0.05 Nm on the Panda, Gaz et al. 2019)
    monitor_slow: tuple = (0.1, 0.6)   # (rad/s, Nm) ours: the monitor also checks an arm slower than this that is not
                                   #   yet calm (returning after a push: 0.5-1 s sooner), for a payload-like level this
                                   #   far from the one explained there (friction leaves up to 0.4 Nm at 0.1 rad/s);
                                   #   refined at rest (0 rad/s: off)
    first_explained: float = 0.97  # the monitor's gate at the first rest, against no payload at all: real loads
                                   #   explain 0.97-1.0 there, the realistic sensor's bias alone about 0.5
    pose_tolerance: float = 0.3    # rad on every joint: within this of the pose where a level was explained, that level
                                   #   still holds (the realistic sensor's bias varies over radians; a 3 kg load
                                   #   or a 60 N push moves the compliant arm by about 0.1-0.3 rad)
    hold_axial: float = 2.5        # s (ours): a change that adds a downward force through the flange's vertical (a
                                   #   person pressing on the hand, or a load centred below the flange: the torques
                                   #   cannot tell them apart) is judged again at rest and estimated only once it has
                                   #   lasted this long (the reliability benchmark's presses last up to 2 s; a longer
                                   #   one is compensated as the load it looks like, withdrawn at its release; 0: at
                                   #   once). A change off that line is estimated at the detection
    axial_radius: tuple = (0.04, 0.012)   # m: "through the flange": its line within this of the flange, while the
                                   #   arm moves (the detection: friction bends a press's wrench by 1-3.6 cm on the
                                   #   realistic plant) and at rest (a press leaves 1-7 mm; a CoM 2 cm off reads 2-2.6)
    max_abs_torque: float = 1e3    # Nm: a sample beyond this, or not finite, is dropped (and counted in `dropped`)
    accumulate: bool = True        # ours: at rest at a new orientation, the same payload, combine the windows seen
    accumulate_angle: float = 0.2  # rad: gravity turned this far in the ee frame since every window kept (rz shows)
    vi: vi.VISettings = field(default_factory=vi.VISettings)
    detector: DetectorSettings = field(default_factory=DetectorSettings)

    def __post_init__(self):
        """Every field checked where it is given (checks.py); the upper bounds keep every product with a rate or a
        torque finite and are far beyond any arm: 10 kHz loops, 50 kg payloads (UR30: 30 kg), 1 m CoMs (the Panda
        reaches 0.855 m), a minute of waiting, torques up to max_abs_torque (<= the detector's MAX_TORQUE)."""
        d, c, top = self.detector, checks, repr(float(checks.number("settings.max_abs_torque", self.max_abs_torque,
                                                                      f"(0, {MAX_TORQUE:g}]", "Nm")))
        keep, settled = checks.instance("settings.detector", d, DetectorSettings).window, d.settled_window[1]
        checks.instance("settings.vi", self.vi, vi.VISettings)
        for name in ("use_network", "asynchronous", "refine", "monitor", "accumulate"):
            c.flag(f"settings.{name}", getattr(self, name))
        c.number("settings.window", self.window, f"20..{keep}", "samples (the detector's window)")
        c.number("settings.reference", self.reference, f"1..{settled}", "samples (the detector checks they precede "
                 "the change)")
        c.number("settings.rate", self.rate, "[10, 1e4]", "Hz")
        c.number("settings.max_mass", self.max_mass, "(0, 50]", "kg")
        c.number("settings.max_com", self.max_com, "(0, 1]", "m")
        c.number("settings.min_explained", self.min_explained, "[0, 1]", "(a share)")
        c.number("settings.first_explained", self.first_explained, "[0, 1]", "(a share)")
        c.number("settings.rest_speed", self.rest_speed, "(0, 1]", "rad/s")
        c.number("settings.refine_within", self.refine_within, "(0, 60]", "s")
        c.number("settings.monitor_threshold", self.monitor_threshold, f"(0, {top})", "Nm")
        c.number("settings.monitor_window", self.monitor_window, f"{self.window}..{keep}", "samples")
        c.number("settings.monitor_far", self.monitor_far, f"({float(self.monitor_threshold)!r}, {top}]",
                 "Nm (above monitor_threshold)")
        c.number("settings.monitor_speed", self.monitor_speed, "(0, 1]", "rad/s")
        slow = c.array("settings.monitor_slow", self.monitor_slow, (2,), f"[0, {top}]",
                       "(speed rad/s, level Nm)")
        if not isinstance(self.monitor_slow, tuple) or not (slow[0] == 0 or self.monitor_speed < slow[0] <= 1) or \
                slow[1] <= self.monitor_threshold:
            raise ValueError(f"settings.monitor_slow: expected (speed, level): a speed of 0 (off) or above "
                             f"monitor_speed up to 1 rad/s and a finite torque above monitor_threshold Nm, found "
                             f"{self.monitor_slow!r}")
        c.number("settings.pose_tolerance", self.pose_tolerance, "(0, 3.1416]", "rad")
        c.number("settings.hold_axial", self.hold_axial, "[0, 60]", "s")
        c.array("settings.axial_radius", self.axial_radius, (2,), "[0, 1]", "m (while moving, at rest)")
        c.number("settings.accumulate_angle", self.accumulate_angle, "(0, 3.1416)", "rad")
        if self.detection_window < 20:
            raise ValueError(f"settings.detector.check_windows: expected an earliest check that leaves at least 20 "
                             f"samples after it (the detection's window), found {d.check_windows}")

    @property
    def detection_window(self) -> int:
        """Samples of the window estimated at a detection: the newest `window`, at most those from the detector's
        earliest stabilisation check on, which it found settled after the change (150 by default; 200 with
        detector.ALGORITHM_1_CHECKS). The estimates at rest and the monitor's take `window`."""
        d = self.detector
        return min(self.window, d.window + 1 - min(w[0] for w in d.check_windows))


def faulty(tau_ext, limit=RMESettings.max_abs_torque) -> bool:
    """Whether a tau_ext sample (n,) is a sensor fault, not a load: not finite, or a joint beyond `limit` [Nm]
    (RME drops it; the robot loop hands its controller the last good sample instead)."""
    return not np.abs(tau_ext).max() <= limit         # (NaN compares False)
