"""The streaming estimator's rules for when to estimate (RME inherits them): at a detection (Alg. 1's event), once
the arm rests after it, for a change held while it may be a press on the hand, and when the consistency monitor finds
a steady level the compensation does not explain (rme_levels: the residual levels by pose that the monitor keeps)."""
from __future__ import annotations

import dataclasses

import numpy as np

import vi
from detector import PAYLOAD_SIDE, payload_like, safe_theta, steady_prefix, through_flange


class Streaming:
    """Mixed into rme.RME, whose state (rings, levels, the compensated estimate) these methods read and set; each
    estimate they start goes through RME._change."""

    def _payload_like(self, d, gate, YJ, mass=None, side=PAYLOAD_SIDE) -> bool:
        """detector.payload_like for a residual change d (n,) at a pose with payload regressor and Jacobian YJ, from
        the payload mass compensated (now)."""
        return payload_like(YJ[0], d, self.theta[0] if mass is None else mass, gate, YJ[1],
                            1.2 * self.settings.max_mass, side)

    def _on_detection(self, asked=None):
        """Estimate the total payload from the newest window, referred to the torque before the change. An accepted
        change during a pending estimate at rest supersedes it. asked: the sample of a detection made during a job.
        With an executor its steps run one per sample (no cycle of the loop carries them all); else all at once."""
        steps = self._detection(asked)
        if self.executor is not None:              # the first step (the window) now, the next ones from the next sample
            self._steps = (steps, self._k) if next(steps, True) is None else None
        else:
            list(steps)                            # all at once

    def _detection(self, asked):
        """_on_detection's steps (a generator: each yield hands the rest to the next sample)."""
        s, w = self.settings, self.settings.detection_window     # w: the samples the detector found settled
        Q, TAU, Rs = self._buffer()
        q_ref, before, asked = Q[:s.reference].mean(axis=0), self.theta.copy(), self._k if asked is None else asked
        held, pending = (self._refine, None) if (self._refine or {}).get("held") else (None, self._refine)
        level = Rs[-w:].mean(axis=0)          # (pending: an estimate at rest is due: refer to before its change)
        if self._lv.undone(Q[-1], level):
            self._held, self._refine = None, pending if held is None else self._resumed(held)
            return                         # back to the level before a change that was no payload: its release
        yield                              # (with an executor each step costs 0.05-0.1 ms in a loop's cold caches)
        steady = steady_prefix(Rs, s.reference, len(Rs) - w) if pending is None else 0
        yield
        bias = pending["bias"] if pending is not None else self._lv.bias(Rs[:steady], q_ref)   # the level before,
        yield                                                                                   # as long as it holds
        _, R, J = self.robot.kinematics(Q[-1])
        YJ, rest = (self.robot.payload_regressor_from(J, R), J), int(np.abs(self._dq).max() < s.monitor_speed)
        if held is not None and self._payload_like(level - held["bias"], s.min_explained, YJ, before[0]) and \
                self._held_back(level - held["bias"], YJ, held["since"], rest):
            self._refine = dict(held, window=(Q[-w:], TAU[-w:]), level=level, asked=asked)
            return                         # the held press, moved a little (the arm yielding to it): still held
        if not self._payload_like(level - bias, s.min_explained, YJ, before[0]):
            self.changes_not_payload, self._lv.rejected = self.changes_not_payload + 1, (q_ref, bias)
            return                         # a push, a bias step
        yield
        known = None if np.linalg.norm(bias) > s.monitor_far else (q_ref, bias)    # the level to leave, unless pushed
        if self._held_back(level - bias, YJ, asked - w, rest):
            self.changes_held, self._lv.rejected = self.changes_held + 1, (q_ref, bias)
            self._refine = dict(bias=bias, known=known, before=before, held=True, since=self._held,   # judged
                                resume=pending if held is None else held["resume"],                     # again at
                                window=(Q[-w:], TAU[-w:]), level=level, asked=asked,                    # rest
                                deadline=self._k + int(s.refine_within * s.rate))
            return
        yield
        Qw, Tw, prepare = Q[-w:], TAU[-w:] - bias, getattr(self.executor, "prepare", None)
        if prepare is not None:            # the window into the worker's shared memory now, the job on the next sample
            prepare(Qw, Tw)
            yield
        def then(e, Y):
            self._lv.rejected = None if e.accepted else (q_ref, bias)   # the level before a change that is no payload
            if e.accepted:                 # a rejected detection (the arm answering a compensation) keeps the last
                self._refine = None        #   pending estimate at rest
            if e.accepted and s.refine:
                self._refine = dict(bias=bias, known=known, before=before,
                                    deadline=self._k + int(s.refine_within * s.rate))
        self._change(Qw, TAU[-w:], bias, before, "detection", then, asked=asked, level=known, Tw=Tw)

    def _on_rest(self, Y, J):
        """Once the arm is still for a window after a detection, estimate again from it (friction no longer holds part
        of the load), unless the change is still there but no payload (a push holds the resting arm: then later). A
        change held at the detection (_held_back; Y, J: update's): released, still held, estimated, or (the arm moving,
        the level moved far from it) gone."""
        s, r, keep = self.settings, self._refine, len(self._r)
        if self._k < r.get("recheck", 0):
            return
        rest = self._still >= s.window or self._calm >= s.monitor_window
        if r.get("held"):                                              # every 10th sample, from the running sums
            if self._k % 10:
                return
            q, level = self._q[(self._k - 1) % keep], self.detector.recent_mean(s.window)
            gap = lambda b: np.linalg.norm(level - b)
            if any(gap(b) <= s.monitor_threshold for b in (r["bias"], self._lv.explained.at(q)) if b is not None):
                self._refine, self._held = self._resumed(r), None      # back to the level before it, or to one the
                return                                                 #   compensation explains here: released
            if gap(r["bias"]) < gap(r["level"]):                       # nearer the level before: the press has gone,
                r = self._refine = dict(r, held=False)                 #   what is left is estimated at rest
                if not rest:
                    return
            elif self._k - r["since"] < s.hold_axial * s.rate and self._k >= self._expected and \
                    self._on_line(level - r["bias"], (Y, J), s.axial_radius[1]):
                return                                                 # (the monitor stays off meanwhile)
        self._refine, self._held = None, None
        why = "" if not r.get("held") else "held as a possible press on the hand (a downward force through the " \
            "flange, as a load centred below it gives) until " + (
                f"it lasted hold_axial = {s.hold_axial:g} s" if self._k - r["since"] >= s.hold_axial * s.rate else
                "the task announced a change" if self._k < self._expected else
                f"its line passed more than {1e3 * s.axial_radius[1]:g} mm from the flange")
        if r.get("held") and not rest:                                 # lasted while the arm moves: the detection's
            if self._moved_on(r, q, level):                            #   window, then again at rest; unless a
                self._refine = self._resumed(r)                        #   push or another change came since: what
                return                                                 #   the window held is gone
            def again(e, Y):
                if e.accepted:
                    e.reason = why                                     # why it is applied only now
                if e.accepted and s.refine:
                    self._refine = dict(r, held=False, deadline=self._k + int(s.refine_within * s.rate))
            return self._change(*r["window"], r["bias"], r["before"], "detection", again, level=r["known"],
                                asked=r["asked"])             # its time (Estimate.t): the end of that window
        level = self.detector.recent_mean(s.window)
        change = level + Y @ (self._phi - vi.phi_of(r["before"])) - r["bias"]
        if np.linalg.norm(change) > s.monitor_threshold and not self._payload_like(   # not gone, but no payload (a
                change, s.min_explained, (Y, J), r["before"][0]):                   #   push holds the resting arm):
            if self._k <= r["deadline"] + 2 * s.refine_within * s.rate and not self._gone(
                    level, (Y, J), self._q[(self._k - 1) % keep]):
                self._refine = dict(r, recheck=self._k + 10)           # again in 10 samples, until the time a moving
            return                                                     # arm is given; not if the load has gone (the
                                                                       # reference held a push): the monitor's then
        Q, TAU, _ = self._buffer()
        withdraw = self._withdraw(r["before"])
        def then(e, Y):
            if e.accepted and why:
                e.reason = why                                         # why it is applied only now
            withdraw(e, Y)
        self._change(Q[-s.window:], TAU[-s.window:], r["bias"], r["before"], "at rest", then, level=r["known"])

    def _moved_on(self, r, q, level) -> bool:
        """Whether the residual `level` (n,) at pose q is no longer the held change r's: farther than monitor_far, or a
        quarter of the change if larger, from that change's payload fit (at its detection's pose) carried to q."""
        d = r["level"] - r["bias"]
        phi = np.linalg.lstsq(self.robot.payload_regressor(r["window"][0].mean(axis=0)), d, rcond=None)[0]
        gap = np.linalg.norm(level - r["bias"] - self.robot.payload_regressor(q) @ phi)
        return bool(gap > max(self.settings.monitor_far, 0.25 * np.linalg.norm(d)))

    def _withdraw(self, before, why=None):
        """then(e, Y) for an estimate at rest: if e finds the change beyond what the arm carries (a press far out, read
        as a plausible load at the detection), the compensation goes back to `before`, the estimate before the change
        (an Estimate of kind "withdrawn" in history). With `why` (its reason): whenever e is refused."""
        def then(e, Y):
            if e.accepted or (why is None and self._plausible(e.mean)) or np.array_equal(self.theta, before):
                return
            w = dataclasses.replace(e, mean=np.array(before, dtype=float), std=np.zeros(4), cov=np.zeros((4, 4)),
                                    observed=np.zeros(4, dtype=bool), seconds=0.0, iterations=0, converged=True,
                                    kind="withdrawn", accepted=True, explained=float("nan"), applied=float("nan"))
            w.reason = why or f"at rest the change is no payload ({e.reason}): back to the estimate before it"
            self.history.append(w)
            self._pending = [self._k, w, None, None]
        return then

    def _gone(self, level, YJ, q) -> bool:
        """Whether the compensated payload is no longer there (a load removed while a push hid the change): the
        residual `level` (n,) at pose q (YJ: its payload regressor and Jacobian) is more than monitor_far from zero
        and from the level explained there, while tau_ext itself (level + the compensation) is nearer zero and within
        monitor_far, as a sensor's bias is. Not if tau_ext is an upward force at the flange (a hand holding the arm
        up), nor if its least-squares payload has 0.1 kg or more, nor at the level where an estimate against no
        payload explained more than half (a small load left: the monitor's usual check estimates it against the level
        known)."""
        s, far = self.settings, np.linalg.norm(level)
        if self.theta[0] <= 0 or far <= s.monitor_far:                 # the common case: the level is explained
            return False
        stays = self._stays.at(q)
        if stays is not None and np.linalg.norm(level - stays) <= s.monitor_threshold:
            return False                         # found a small load left here: the monitor's usual check
        bare, known = level + YJ[0] @ self._phi, self._lv.explained.at(q)
        return bool(np.linalg.norm(bare) < min(s.monitor_far, far) and (
            known is None or np.linalg.norm(level - known) > s.monitor_far) and not self._payload_like(
            -bare, s.min_explained, YJ, 0.0) and np.linalg.lstsq(YJ[0], bare, rcond=None)[0][0] < 0.1)

    def _resumed(self, held):                      # the estimate at rest a held change superseded, due from now
        r, s = held["resume"], self.settings
        return None if r is None else dict(r, deadline=self._k + int(s.refine_within * s.rate))

    def _check_consistency(self, Y, J, moving=False):
        """The monitor (see update): the residual's level over the last monitor_window samples, if steady, against
        the level explained before at this pose. The very first level is estimated against no payload at all (RME
        assumes it starts unloaded) with the stricter gate first_explained; at a pose never seen, the level is
        taken as explained, unless it is monitor_far from the nearest level known (rme_levels.Levels.judge). If the
        compensated payload has gone (_gone), the level is estimated against no payload: applied if a clear payload
        (first_explained), the compensation withdrawn if it explains under half (a bias), else the level is left to
        the usual check. Y, J: the payload regressor and Jacobian of the current sample (update's), where a payload
        is tested.
        moving: the arm is slower than monitor_slow[0] but not calm (returning after a push, say): the level over the
        last `window` samples, estimated only if it is a payload-like change of more than monitor_slow[1] (monitor_far
        while an estimate at rest is due: friction during the creep after a compensation is its to judge) from the
        level explained at this pose and off the flange's line (a press is judged at rest; on it too while the task
        expects a change: RME.expect_change), and refined once the arm rests; at a pose where no level was
        explained, of more than monitor_far from the nearest level known (no payload if none is: an arm never calm
        yet). Nothing is kept from such a check (friction still holds a few tenths of a Nm) but a level whose estimate
        was refused: not tried again while it stays (the check at rest judges it once the arm is calm)."""
        s = self.settings
        span = s.window if moving else s.monitor_window               # the residual's means from the detector's
        level, recent = self.detector.recent_mean(span), self.detector.recent_mean(span // 3)   # sums: O(1)
        if np.linalg.norm(recent - level) > 0.5 * s.monitor_threshold:
            return                                                     # still changing: not a level yet
        q = self._q[(self._k - span + np.arange(span)) % len(self._q)].mean(axis=0)
        first_gate = s.first_explained if self.theta[0] <= 0 else s.min_explained   # strict only if nothing compensated
        if not moving and self._gone(level, (Y, J), q):   # against no payload at all: a clear payload, else none left
            Q, TAU, _ = self._buffer()
            bare, none = TAU[-s.window:].mean(axis=0), np.zeros(4)
            gone = self._withdraw(none, "at rest tau_ext is a sensor's bias, not the payload compensated")
            def keep(e, Y):
                if e.accepted:                   # a payload after all, estimated against none: it leaves the bias
                    self._pending[2] = (q, bare - Y @ vi.phi_of(e.mean))
                elif e.explained >= 0.5:         # more than a bias explains: a small load left, for the usual check
                    self._stays.put(q, level)    #   against the level known (a bias explains about half)
                else:
                    gone(e, Y)
            self._change(Q[-s.window:], TAU[-s.window:], np.zeros(len(level)), none, "monitor", keep,
                         lambda e, Tw, Y: e.explained >= s.first_explained)
            self._calm = 0
            return
        if moving:
            trusted, kind, gate = self._lv.explained.at(q), "level", s.min_explained
            if trusted is None:                  # a pose never seen (a push moved the arm): against the nearest
                trusted, kind = self._lv.explained.at(q, anywhere=True), "far"   # level known if monitor_far off;
            if trusted is None:                  # none (an arm never calm yet): against no payload, with the first
                trusted, kind, gate = np.zeros(len(level)), "blank", first_gate  # level's gate (nothing is kept)
            same = lambda b: b is not None and np.linalg.norm(level - b) <= s.monitor_threshold
            least = s.monitor_slow[1] if self._refine is None and kind == "level" else s.monitor_far   # with an
            if (np.linalg.norm(level - trusted) <= least                         # estimate at rest due, only a new
                    or same(self._lv.muted.at(q)) or same(self._slow_rejected.at(q))   # change, not its creep
                    or (self._k >= self._expected and self._on_line(level - trusted, (Y, J), s.axial_radius[0]))
                    or not self._payload_like(level - trusted, gate, (Y, J))):
                return
            verdict = (trusted, kind)
        else:                                    # the first level holds the sensor's unknown bias: its side force
            blank = (s.detector.side_force_limit, PAYLOAD_SIDE[1])    # too (tested against no payload at all)
            verdict = self._lv.judge(q, level, lambda d, gate, none=False: self._payload_like(
                d, gate, (Y, J), side=blank if none else PAYLOAD_SIDE), (first_gate, s.min_explained), s.monitor_far)
        if verdict == "new" and s.accumulate and self._evidence and self.theta[0] > 0.05 and self._turned(q):
            Q, TAU, _ = self._buffer()           # the same payload seen from a new side: combine the evidence
            same = lambda e, Tw, Y: abs(e.mean[0] - self.theta[0]) <= max(0.1 * self.theta[0], 0.05)
            self._change(Q[-s.window:], TAU[-s.window:], self._evidence[0][2], self.theta, "accumulated",
                         self._leaves(q, level), same, evidence=self._evidence)   # referred like the first window
            self._calm = self._slow = 0
        if verdict is None:
            self._held = None
        held, before = self._held is not None, self.theta.copy()    # a change held that is let go now: estimated
        if verdict is None or verdict == "new" or (not moving and self._held_back(   # again at rest (see then);
                level - verdict[0], (Y, J), self._k - span, int(verdict[1] != "renewed"))):
            return                  # against none after a doubtful level, whose bias bends a press's wrench as
                                    #   friction does: the wider line
        (reference, kind), first = verdict, verdict[1] in ("first", "renewed")
        Q, TAU, _ = self._buffer()               # the window to estimate on (correction applied)
        if first or kind == "blank":             # against no payload: only a clear payload counts
            accept = lambda e, Tw, Y: e.explained >= first_gate
        else:                                    # the new estimate must make the level consistent again: within
            gap = np.linalg.norm(level - reference)  # 6 % of a large gap (a heavy load's sag moves the bias); far from
            tol = 0.25 * gap if kind == "far" else min(max(s.monitor_threshold, 0.06 * gap),   # any pose: 3/4
                                                       0.5 * gap)
            accept = lambda e, Tw, Ybar: np.linalg.norm(Tw.mean(axis=0) - Ybar @ vi.phi_of(safe_theta(
                e.mean, self.theta, s.max_mass))) <= tol
        def then(e, Y):
            if e.accepted and first:                                   # what the payload leaves is the bias
                self._pending[2] = (q, TAU[-s.window:].mean(axis=0) - Y @ vi.phi_of(e.mean))
            elif first:
                self._lv.take_bias(q, level, s.monitor_far)                # no payload: the level is the bias
                self.history.pop()                                     # (establishing it is not an estimate)
            elif kind == "far" and not moving:                         # (moving: friction in the level)
                self._leaves(q, level)(e) if e.accepted else self._lv.muted.put(q, level)
            elif not e.accepted and not moving:
                self._lv.muted.put(q, level)
            elif not e.accepted:                                       # not again while it stays (the check at
                self._slow_rejected.put(q, level)                      #   rest still judges it once calm)
            if e.accepted and (held or moving) and s.refine:
                self._refine = dict(bias=reference, known=None if kind != "level" else (q, reference), before=before,
                                    deadline=self._k + int(s.refine_within * s.rate))
        self._change(Q[-s.window:], TAU[-s.window:], reference, self.theta, "monitor", then, accept,
                     level=None if kind != "level" else (q, reference))
        self._slow = 0
        if not moving:
            self._calm = 0

    def _held_back(self, d, YJ, since, rest) -> bool:
        """Whether a payload-like change d (n,) waits: it may be a hand on the flange (_on_line; YJ: the payload
        regressor and the flange's Jacobian; rest 0/1: the arm moves/rests, picks axial_radius) and has lasted less
        than hold_axial since self._held (set to `since`, the sample it began by, if None; cleared when such a change
        goes)."""
        s = self.settings
        if s.hold_axial <= 0 or self._k < self._expected or not self._on_line(d, YJ, s.axial_radius[rest]):
            self._held = None                                          # (a change the task expects: not held)
            return False
        self._held = since if self._held is None else self._held
        return self._k - self._held < s.hold_axial * s.rate

    def _on_line(self, d, YJ, radius) -> bool:
        """Whether a change d (n,) may be a person's hand on the flange: it adds a downward force whose line passes
        within `radius` of it (through_flange: a press, or a load centred below the flange), unless, within hold_axial
        of a change read as part of the load gone (at least 0.1 kg left), it takes the compensation back to the
        estimate before that change (within a quarter): its end, as when a person lets go of a load they had lifted
        by the hand. (After a whole load is gone, a press like it is still held.) YJ: the payload regressor and the
        flange's Jacobian."""
        if self._undo is not None and self._k <= self._undo[1]:
            back = YJ[0] @ (self._undo[0] - self._phi)
            if np.linalg.norm(back) > self.settings.monitor_threshold and \
                    np.linalg.norm(d - back) <= 0.25 * np.linalg.norm(back):
                return False
        return through_flange(YJ[1], d, radius)

    def _leaves(self, q, level):
        """then(e, Y) for an estimate at pose q, residual level `level` now: once accepted, what it leaves is
        explained."""
        Yq, phi = self.robot.payload_regressor(q), self._phi.copy()
        return lambda e, Y=None: e.accepted and self._lv.explained.put(q, level - Yq @ (vi.phi_of(safe_theta(
            e.mean, self.theta, self.settings.max_mass)) - phi))

    def _turned(self, q) -> bool:
        """Whether gravity, seen from the ee at pose q, has turned by accumulate_angle from every window kept."""
        g = lambda x: self.robot.ee_pose(x)[1][2]             # the world z axis in the ee frame
        return all(np.arccos(np.clip(g(q) @ g(Q.mean(axis=0)), -1, 1)) > self.settings.accumulate_angle for Q, *_ in
                   self._evidence)
