"""The residual levels a streaming estimator keeps by pose (RME's consistency monitor): LevelMap, one kind of level
by pose, and Levels, what a steady level at a pose means (explained, no payload, a change to estimate)."""
from __future__ import annotations

import numpy as np


class LevelMap:
    """Residual levels (n,) by pose: the torque the arm's own sensors and model error leave at a pose q (n,) when
    the compensation is right (a real Panda's bias is pose dependent). at(q): the level stored nearest to q within
    `tolerance` rad on every joint, or None; put(q, level, anchor) replaces that one or adds it (at most `size`
    kept); anchor_at(q): the level it had when it was last put without an anchor (followed since: see Levels.judge)."""

    def __init__(self, tolerance: float, size: int = 64):
        self.tolerance, self.size, self.q, self.level, self.anchor = tolerance, size, [], [], []
        self._qa = None                                        # self.q as an array, while no put changes it

    def __len__(self):
        return len(self.q)

    def _nearest(self, q, anywhere=False):
        if not self.q:
            return None
        if self._qa is None:                                   # the poses as one array, rebuilt after a change
            self._qa = np.array(self.q)
        d = np.abs(self._qa - q).max(axis=1)
        i = int(np.argmin(d))
        return i if anywhere or d[i] <= self.tolerance else None

    def at(self, q, anywhere=False):
        """The level stored nearest to q within `tolerance` (anywhere: whatever the distance), or None."""
        i = self._nearest(q, anywhere)
        return None if i is None else self.level[i]

    def anchor_at(self, q, anywhere=False):
        i = self._nearest(q, anywhere)
        return None if i is None else self.anchor[i]

    def put(self, q, level, anchor=None):
        i = self._nearest(q)
        if i is not None:
            del self.q[i], self.level[i], self.anchor[i]
        self.q.append(np.array(q, dtype=float))
        self.level.append(np.array(level, dtype=float))
        self.anchor.append(self.level[-1] if anchor is None else np.array(anchor, dtype=float))
        if len(self.q) > self.size:
            del self.q[0], self.level[0], self.anchor[0]
        self._qa = None


class Levels:
    """The residual levels a streaming estimator keeps by pose (LevelMaps within `tolerance` rad): `explained`, where
    the compensated estimate explained tau_ext; `muted`, steady levels found not to be a payload; `rejected`, the
    (q, level) before the last change that was no payload. `threshold` [Nm]: levels closer than this are the same."""

    def __init__(self, tolerance: float, threshold: float):
        self.tolerance, self.threshold = tolerance, threshold
        self.explained, self.muted, self.rejected = LevelMap(tolerance), LevelMap(tolerance), None
        self.doubtful = False          # the first level, taken as the bias, is no payload but too far from zero for one
        self.renewing = False          # no level explained since a doubtful one was forgotten: each is "renewed"

    def undone(self, q, level) -> bool:
        """Whether the residual `level` at pose q is back within `threshold` of the level before the last rejected
        change, at that pose: the end of whatever caused it (a person releasing the arm). Forgets that change then."""
        if self.rejected is None:
            return False
        q0, before = self.rejected
        back = np.abs(q - q0).max() <= self.tolerance and np.linalg.norm(level - before) <= self.threshold
        if back:
            self.rejected = None
        return back

    def judge(self, q, level, is_payload, gates, far):
        """What a steady residual `level` (n,) at pose q means (is_payload(d, gate, none) -> bool: payload_like for a
        change d there, none: d is against no payload at all, the sensor's bias in it; called only if a payload must
        be tested; gates: (first, later) explained shares): None when it needs nothing (explained here: the level is
        followed; judged before; no payload), "new" at a pose never seen (taken as explained) unless the level is more
        than `far` [Nm] from the nearest level known (no sensor bias reaches that: a change missed while a push moved
        the arm), else (reference, kind) to estimate against: kind "first" (the very first level, against no
        payload), "level" (the level explained here), "far", or "renewed": a first level that is no payload yet more
        than `far` from zero (a person holding the arm from the start, a tool) is doubtful (take_bias); a later level
        that is no payload against it but a clear one against none is estimated against none, as a new first level,
        and every level explained so far, at every pose, is forgotten (until a level is kept again, each is
        "renewed")."""
        near = lambda a, b: b is not None and np.linalg.norm(a - b) <= self.threshold
        trusted, first = self.explained.at(q), len(self.explained) == 0
        if near(level, self.muted.at(q)):
            return None                                                # judged before: not a payload
        kind = ("renewed" if self.renewing else "first") if first else "level"
        if not first and trusted is None:
            trusted, kind = self.explained.at(q, anywhere=True), "far"
            if np.linalg.norm(level - trusted) <= far:
                self.explained.put(q, level)
                return "new"
        elif not first and near(level, trusted):
            anchor = self.explained.anchor_at(q)
            if near(level, anchor):                                    # explained: follow the slow bias drift, as
                self.explained.put(q, level, anchor)                   # far as threshold from where it was explained
                return None
            trusted = anchor           # beyond: a slow change (friction letting go of a load's part as the arm creeps)
        reference = np.zeros(len(level)) if first else trusted
        if is_payload(level - reference, gates[0] if first else gates[1], first):
            return reference, kind
        if first:
            self.take_bias(q, level, far)                              # the bias; or e.g. a person holding the arm
        elif self.doubtful and is_payload(level, gates[0], True):      # a clear payload against none at all: that
            self.explained, self.doubtful, self.renewing = LevelMap(self.tolerance), False, True   # first level was
            return np.zeros(len(level)), "renewed"                                                 # no bias (a push)
        else:
            self.muted.put(q, level)
        return None

    def take_bias(self, q, level, far):
        """Keep the first level (n,) at pose q as the sensor's bias; doubtful if more than `far` [Nm] from zero,
        which no sensor's bias is (a person holding the arm, a tool held from the start)."""
        self.explained.put(q, level)
        self.doubtful, self.renewing = bool(np.linalg.norm(level) > far), False

    def bias(self, R_ref, q_ref):
        """What tau_ext holds beyond the compensated payload before a change: the mean residual of the reference
        samples R_ref (T, n) taken at pose q_ref, unless the estimate did not explain them (a push, a change it
        missed) while a level it did explain is known at that pose: then that level."""
        local, trusted, muted = R_ref.mean(axis=0), self.explained.at(q_ref), self.muted.at(q_ref)
        if trusted is None or np.linalg.norm(local - trusted) <= self.threshold:
            return local
        if muted is not None and np.linalg.norm(local - muted) <= self.threshold:
            return local                     # a state already judged not to be a payload (a drifted bias)
        return trusted
