"""Robot logs for model diagnosis: read .npz, libfranka logger or lab CSV logs (formats and units: load_log), drop
bad and stale rows, resample, smooth (Savitzky-Golay) and differentiate; write .npz / CSV. tau_ext in the paper's
sign (Eq. 1, tau_ext = model - tau_J); libfranka's tau_ext_hat_filtered (= tau_J - model) is flipped on load."""
from __future__ import annotations

import csv
import dataclasses
import os
import re
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import savgol_filter

SIGNS = ("paper", "libfranka")                 # tau_ext conventions a log may declare
TIME_COLUMNS = {"t": 1.0, "time": 1.0, "time_s": 1.0, "timestamp": 1.0,      # s per unit of each time column
                "t_ms": 1e-3, "time_ms": 1e-3, "duration": 1e-3}              # duration: ms since the start (lab)
LIBFRANKA_TIME = 1e-3                          # franka::logToCSV writes `time` as RobotState::time.toMSec(): ms


@dataclass(frozen=True)
class LogConfig:
    """How a raw log becomes a uniform, differentiated one."""
    dt: float | None = None        # s, resampling period; None: the median stamp difference (1 ms on a Panda)
    sg_window: float = 0.05        # s, Savitzky-Golay window (51 samples at 1 kHz; passes the < 5 Hz of arm motion)
    sg_order: int = 3              # polynomial order of the Savitzky-Golay fit
    min_samples: int = 200         # fewer samples left after cleaning: too short to fit (0.2 s at 1 kHz)
    drop_nan: bool = False         # rows with NaN/inf: False raises ValueError, True drops them (counted in info)
    max_gap: float = 0.05          # s, longest time step interpolated over; real 1 kHz logs step 0.7-8.8 ms
                                   # (panda_facts.md); a longer gap is refused, one sg_window without data
    max_bad_rows: float = 0.01     # fraction of CSV data rows that may be malformed (a wrong number of fields or a
                                   # non-number): dropped and counted in info["bad_rows"]; more raises ValueError
    max_angle: float = 4 * np.pi   # rad, |q| beyond: two turns, not a joint angle (degrees read as radians?)
    max_speed: float = 50.0        # rad/s, |dq| beyond: 20x the Panda's 2.2-2.6 rad/s limits (panda_facts.md)
    max_torque: float = 1000.0     # Nm, |tau_J|, |tau_ext| beyond: 11x the Panda's 87 Nm limit; not a joint torque


@dataclass(frozen=True)
class Log:
    """A uniform log: t (T,) [s]; q, dq, ddq (T, n) [rad, rad/s, rad/s^2]; tau_J and tau_ext (T, n) [Nm] or None,
    tau_ext in the paper's sign. info: what loading did (source, time column, malformed, NaN and stale rows
    dropped, dt, filter)."""
    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    tau_J: np.ndarray | None
    tau_ext: np.ndarray | None
    info: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return self.q.shape[1]

    def __len__(self) -> int:
        return self.t.shape[0]

    def rows(self, index) -> "Log":
        """The log restricted to rows `index` (a slice, boolean mask or integer array)."""
        pick = lambda a: None if a is None else a[index]
        return dataclasses.replace(self, t=self.t[index], q=self.q[index], dq=self.dq[index],
                                   ddq=self.ddq[index], tau_J=pick(self.tau_J), tau_ext=pick(self.tau_ext))


# --- reading -----------------------------------------------------------------------------------------
def load_log(path, config: LogConfig = LogConfig()) -> Log:
    """Read a robot log and prepare it (see prepare). Accepted files, tau_ext always returned in the paper's sign:

    - .npz: t [s], q, dq [rad, rad/s], optional ddq, tau_J and/or tau_ext [Nm] (T, n) (read_npz);
    - CSV with a header line of comma-separated column names and one row per sample (read_csv):
      * libfranka's logger (franka::logToCSV): `time` in ms, `state.q[i]`, `state.dq[i]`, `state.tau_J[i]`,
        `state.tau_ext_hat_filtered[i]` (libfranka sign, flipped), other state./cmd. columns ignored;
      * q[i] (or q_i) style names with `t`/`time`/`time_s`/`timestamp` in s, `t_ms`/`time_ms` in ms, or a lab
        logger's `duration` in ms since the start; rows with a wrong number of fields or a non-number are dropped
        and counted in info["bad_rows"] (their file lines in info["bad_lines"]), up to config.max_bad_rows.
    A time gap longer than config.max_gap is refused with ValueError (not split, not interpolated)."""
    raw, notes = read_log(path, config)
    return prepare(raw, config, source=os.fspath(path), notes=notes)


def read_log(path, config: LogConfig = LogConfig()) -> tuple[dict, dict]:
    """(raw arrays, notes) of a log file as load_log reads it, before prepare (formats and errors: load_log)."""
    try:
        path = os.fspath(path)
    except TypeError:
        raise ValueError(f"path: expected a log file path (str or os.PathLike), found {type(path).__name__} "
                         f"{path!r}") from None
    if not os.path.isfile(path):
        raise ValueError(f"path: expected a log file (.npz or .csv), found no file at {path!r}")
    ext = os.path.splitext(path)[1].lower()
    if ext == ".npz":
        raw, notes = read_npz(path), {"format": "npz", "time_column": "t [s]", "bad_rows": 0}
    elif ext == ".csv":
        raw, notes = read_csv(path, config.max_bad_rows)
    else:
        raise ValueError(f"path: expected a .npz or .csv log, found extension {ext!r}")
    return raw, notes


def read_npz(path) -> dict:
    """Raw arrays of an .npz log: t, q, dq, optional ddq, tau_J and/or tau_ext (converted to the paper's sign using
    the optional key tau_ext_sign, default "paper"; a key tau_ext_hat_filtered is taken as libfranka's sign)."""
    try:
        z = np.load(path, allow_pickle=False)
    except Exception as err:                       # empty, truncated, not a zip, pickled objects ...
        raise ValueError(f"path: could not read the log {path!r} as .npz: {type(err).__name__}: {err}") from None
    with z:
        def column(k):
            return real_array(k, z[k], f" in {path!r}")
        raw = {k: column(k) for k in ("t", "q", "dq", "ddq", "tau_J") if k in z}
        sign = str(z["tau_ext_sign"]) if "tau_ext_sign" in z else "paper"
        if sign not in SIGNS:
            raise ValueError(f"tau_ext_sign: expected one of {SIGNS}, found {sign!r}")
        if "tau_ext" in z:
            raw["tau_ext"] = column("tau_ext") * (1.0 if sign == "paper" else -1.0)
        elif "tau_ext_hat_filtered" in z:
            raw["tau_ext"] = -column("tau_ext_hat_filtered")
    return raw


def real_array(name: str, v, where: str = "") -> np.ndarray:
    """v as a float array; ValueError naming `name` for anything but real numbers (complex, bool, text, objects)."""
    a = np.asarray(v)
    if a.dtype.kind not in "fiu":
        raise ValueError(f"{name}: expected real numbers{where}, found dtype {a.dtype}"
                         + (" (complex values are not torques or angles)" if a.dtype.kind == "c" else ""))
    return a.astype(float)


def read_csv(path, max_bad_rows: float = LogConfig.max_bad_rows) -> tuple[dict, dict]:
    """(raw arrays, notes) of a CSV log (formats: load_log). Columns are joint vectors name[i] or name_i, with an
    optional `state.` prefix (libfranka's logger; `cmd.` columns are kept apart and unused), and one time column.
    Empty cells read as NaN (see LogConfig.drop_nan); malformed rows are dropped and counted in notes."""
    names = _csv_header(path)
    groups, time_col, libfranka = _csv_columns(names, path)
    n = len(groups.get("q", {}))
    missing = [] if time_col else [f"a time column ({', '.join(TIME_COLUMNS)})"]
    for key in ("q", "dq"):
        missing += [f"{key}[{i}]" for i in range(max(n, 1)) if i not in groups.get(key, {})]
    torques = [k for k in ("tau_J", "tau_ext_hat_filtered", "tau_ext") if k in groups]
    if not torques:
        missing.append("tau_J[..] and/or tau_ext_hat_filtered[..]")
    for key in torques + (["ddq"] if "ddq" in groups else []):
        missing += [f"{key}[{i}]" for i in range(n) if i not in groups[key]]
    if missing:
        raise ValueError(f"csv: missing columns {', '.join(missing)} in {path!r}")
    body, bad_lines = _csv_body(path, len(names), max_bad_rows)
    col, name = time_col
    scale = LIBFRANKA_TIME if libfranka and name == "time" else TIME_COLUMNS[name]
    raw = {"t": body[:, col] * scale}
    for key in ("q", "dq", "ddq", "tau_J", "tau_ext"):
        if key in groups:
            raw[key] = body[:, [groups[key][i] for i in range(n)]]
    if "tau_ext_hat_filtered" in groups and "tau_ext" not in raw:
        raw["tau_ext"] = -body[:, [groups["tau_ext_hat_filtered"][i] for i in range(n)]]   # libfranka sign
    unit = "ms" if scale == 1e-3 else "s"
    notes = {"format": "libfranka logger" if libfranka else "csv", "time_column": f"{name} [{unit}]",
             "bad_rows": len(bad_lines), "bad_lines": bad_lines[:10]}
    return raw, notes


def _csv_header(path):
    """Stripped column names of the first line of a CSV file."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:      # -sig: a spreadsheet's byte-order mark
            header = next(csv.reader(f), None)
            rows = sum(1 for line in f if line.strip())
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"path: could not read the log {path!r} as CSV text: {type(err).__name__}: {err}") from None
    if not header:
        raise ValueError(f"csv: expected a header row in {path!r}, found an empty file")
    if rows == 0:
        raise ValueError(f"log: expected data rows, found none (a header only) in {path!r}")
    return [h.strip() for h in header]


def _csv_body(path, width, max_bad_rows):
    """(body (R, width), file line numbers of the dropped malformed rows). Empty cells read as NaN."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")             # any loadtxt complaint: parse row by row below
        try:                                       # fast path: a clean file
            body = np.loadtxt(path, delimiter=",", skiprows=1, dtype=float, ndmin=2)
            if body.shape[1] == width:
                return body, []
        except (ValueError, UserWarning):
            pass
    rows, bad = [], []
    with open(path, newline="", encoding="utf-8-sig") as f:
        reader = csv.reader(f)
        next(reader)
        for cells in reader:
            if not any(c.strip() for c in cells):
                continue                           # blank line
            try:
                if len(cells) != width:
                    raise ValueError(f"{len(cells)} fields, expected {width} as in the header")
                rows.append([float(c) if c.strip() else np.nan for c in cells])
            except ValueError as err:
                bad.append((reader.line_num, str(err)))
    total = len(rows) + len(bad)
    if len(bad) > max_bad_rows * total:
        line, why = bad[0]
        raise ValueError(f"csv: {len(bad)} of {total} data rows of {path!r} are malformed (first at line {line}: "
                         f"{why}); expected at most a fraction max_bad_rows = {max_bad_rows} (is the delimiter a "
                         "comma and the decimal mark a point?)")
    return np.array(rows, dtype=float).reshape(-1, width), [line for line, _ in bad]


def _csv_columns(names, path):
    """({joint-vector name: {index: column}}, (time column, its name) or None, libfranka logger header?)."""
    groups, time_col, libfranka = {}, None, False
    for col, name in enumerate(names):
        m = re.fullmatch(r"(?:(state|cmd)\.)?([A-Za-z_]+?)(?:\[(\d+)\]|_(\d+))", name)
        if m:
            libfranka |= m.group(1) == "state"
            key = m.group(2) if m.group(1) in (None, "state") else f"{m.group(1)}.{m.group(2)}"
            i = int(m.group(3) or m.group(4))
            if i in groups.setdefault(key, {}):
                raise ValueError(f"csv: expected each column once, found {name!r} in columns "
                                 f"{groups[key][i]} and {col} of {path!r}")
            groups[key][i] = col
        elif name in TIME_COLUMNS and time_col is None:
            time_col = (col, name)
    return groups, time_col, libfranka


# --- preparing ---------------------------------------------------------------------------------------
def prepare(raw: dict, config: LogConfig = LogConfig(), source: str = "arrays", notes: dict | None = None) -> Log:
    """Check a raw log and make it uniform: NaN rows -> error (or dropped, counted), stale repeats dropped, time
    checked strictly increasing and free of gaps longer than config.max_gap (ValueError naming the gap; the log
    is not split), resampled onto t0 + k dt by linear interpolation; then, unless the log has ddq,
    one Savitzky-Golay smoother on dq and on the torques, and ddq = central differences of the smoothed dq, so
    tau_J and M ddq pass the same filter (parallel filtering; regressors of sharp effects get it too, effects.py).

    Stale rule: a row whose q, dq and tau_J (tau_ext if no tau_J) all equal the previous row's exactly is a repeated
    packet and is dropped, whatever its time stamp (a real sensor's noise never repeats 3n values; an arm truly at
    rest loses nothing, since interpolation restores the same values), so a gap is measured between the recorded
    time stamps, stale rows included. notes: what reading the file found (load_log), copied into info."""
    raw = _check_raw(raw)
    info = {"source": source, "rows": len(raw["t"]), "bad_rows": 0, **(notes or {})}
    raw, info["nan_rows"] = _drop_nan(raw, config.drop_nan)
    _check_ranges(raw, config)
    keep = ~_stale_rows(raw)
    info["stale_rows"] = int((~keep).sum())
    t, out, info["dt"], info["resampled"] = _resample({k: v[keep] for k, v in raw.items()}, config, raw["t"],
                                                         info)
    win = 2 * int(round(config.sg_window / info["dt"] / 2)) + 1
    if win <= config.sg_order or win > len(t):
        raise ValueError(f"config.sg_window: expected between {config.sg_order + 1} samples and the log "
                         f"length {len(t)}, found {win} samples ({config.sg_window} s at dt = {info['dt']} s)")
    if "ddq" in out:
        info.update(smoothing=None, filter="none (ddq from the log)")
    else:
        smooth = lambda x: savgol_filter(x, win, config.sg_order, axis=0, mode="interp")
        out["ddq"] = np.gradient(smooth(out["dq"]), info["dt"], axis=0)
        out.update({k: smooth(out[k]) for k in ("tau_J", "tau_ext") if k in out})
        info.update(smoothing=(win, config.sg_order), filter=f"Savitzky-Golay order {config.sg_order}, {win} samples "
                    f"({win * info['dt']:.3f} s) on the torques and on dq, then central differences for ddq")
    return Log(t=t, q=out["q"], dq=out["dq"], ddq=out["ddq"], tau_J=out.get("tau_J"), tau_ext=out.get("tau_ext"),
               info=info)


def missing_cycles(stamps, dt) -> dict:
    """The cycles a log missed, all filled in by interpolation: {gaps: steps of the recorded stamps (T0,) longer than
    1.5 dt, missing_cycles: the periods dt missing in them, longest_gap [s] and gap_at [s] where it starts}."""
    step = np.diff(stamps)
    gaps = np.flatnonzero(step > 1.5 * dt)
    missing = int(np.sum(np.round(step[gaps] / dt) - 1)) if len(gaps) else 0
    i = int(gaps[np.argmax(step[gaps])]) if len(gaps) else None
    return {"gaps": int(len(gaps)), "missing_cycles": missing,
            "longest_gap": float(step[i]) if i is not None else 0.0,
            "gap_at": float(stamps[i]) if i is not None else None}


def _resample(raw, config, stamps, info):
    """(t (G,), arrays on the grid, dt, resampled?) after checking the length and the time stamps (stamps (T0,): all
    recorded ones, stale rows included, for the gap check); the missing cycles go into info."""
    t = raw["t"]
    if len(t) < config.min_samples:
        raise ValueError(f"log: too short to fit: {len(t)} samples after cleaning, expected at least "
                         f"{config.min_samples}")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        i = int(bad[0]) + 1
        raise ValueError(f"t: expected strictly increasing time stamps, found t[{i}] = {t[i]!r} after "
                         f"t[{i - 1}] = {t[i - 1]!r} ({len(bad)} such rows)")
    _check_gaps(t, stamps, config.max_gap)
    dt = float(np.median(np.diff(t))) if config.dt is None else float(config.dt)
    if not dt > 0:
        raise ValueError(f"config.dt: expected a period > 0 s, found {dt}")
    info.update(missing_cycles(stamps, dt))
    span = (t[-1] - t[0]) / dt + 1e-6          # slack: stamps like 3600.123 s (a robot clock) carry ~1e-13 s error
    grid = t[0] + dt * np.arange(int(np.floor(span)) + 1)
    if len(grid) == len(t) and np.allclose(grid, t, rtol=0, atol=1e-6 * dt):
        return t, {k: v for k, v in raw.items() if k != "t"}, dt, False
    return grid, {k: _interp(grid, t, v) for k, v in raw.items() if k != "t"}, dt, True


def _check_gaps(t, stamps, max_gap):
    """ValueError if the recorded stamps (T0,) leave a gap longer than max_gap [s]; t (T,): the kept stamps."""
    if not max_gap > 0:
        raise ValueError(f"config.max_gap: expected a duration > 0 s, found {max_gap}")
    step = float(np.median(np.diff(t)))
    if step > max_gap:
        raise ValueError(f"t: expected a sampling period below config.max_gap = {max_gap} s, found a median step of "
                         f"{step:g} s (time stamps in ms read as s?)")
    gaps = np.flatnonzero(np.diff(stamps) > max_gap)
    if len(gaps):
        i = int(gaps[0])
        raise ValueError(f"t: expected no gap longer than config.max_gap = {max_gap} s, found {len(gaps)}, the first "
                         f"of {stamps[i + 1] - stamps[i]:g} s from t = {stamps[i]:.10g} s to {stamps[i + 1]:.10g} s "
                         f"(samples {i} and {i + 1}); cut the log at the gap, or raise max_gap to interpolate over it")


def _check_raw(raw):
    missing = [k for k in ("t", "q", "dq") if k not in raw]
    if "tau_J" not in raw and "tau_ext" not in raw:
        missing.append("tau_J and/or tau_ext")
    if missing:
        raise ValueError(f"log: missing {', '.join(missing)}; found keys {sorted(raw)}")
    out = {k: real_array(k, v) for k, v in raw.items()
           if k in ("t", "q", "dq", "ddq", "tau_J", "tau_ext") and v is not None}
    t = out["t"] = out["t"].reshape(-1) if out["t"].ndim == 2 and 1 in out["t"].shape else out["t"]
    if t.ndim != 1:
        raise ValueError(f"t: expected shape (T,), found {t.shape}")
    if len(t) == 0:
        raise ValueError("log: expected data rows, found none (a header or empty arrays only)")
    if out["q"].ndim != 2 or out["q"].shape[1] < 1:
        raise ValueError(f"q: expected shape (T, n), found {out['q'].shape}")
    n = out["q"].shape[1]
    for k, v in out.items():
        want = (len(t),) if k == "t" else (len(t), n)
        if v.shape != want:
            raise ValueError(f"{k}: expected shape {want} to match t and q, found {v.shape} (mismatched lengths)")
    return out


def _check_ranges(raw, config):
    """ValueError naming the first value beyond what a joint angle, speed or torque can be (config's max_*)."""
    limits = {"q": (config.max_angle, "rad"), "dq": (config.max_speed, "rad/s"), "tau_J": (config.max_torque, "Nm"),
              "tau_ext": (config.max_torque, "Nm")}
    for k, (limit, unit) in limits.items():
        if k in raw and np.any(np.abs(raw[k]) > limit):
            row, j = np.argwhere(np.abs(raw[k]) > limit)[0]
            raise ValueError(f"{k}: expected |{k}| <= {limit:g} {unit}, found {raw[k][row, j]:g} at row {row}, "
                             f"joint {j + 1} ({int(np.sum(np.abs(raw[k]) > limit))} such values)")


def _drop_nan(raw, drop):
    bad = np.zeros(len(raw["t"]), bool)
    for v in raw.values():
        bad |= ~np.all(np.isfinite(v.reshape(len(bad), -1)), axis=1)
    if bad.any() and not drop:
        first = int(np.flatnonzero(bad)[0])
        cols = [k for k, v in raw.items() if not np.all(np.isfinite(v[first]))]
        raise ValueError(f"log: {int(bad.sum())} rows contain NaN/inf (first at row {first}, in {', '.join(cols)}); "
                         "drop them with LogConfig(drop_nan=True) (CLI: --drop-nan)")
    return ({k: v[~bad] for k, v in raw.items()} if bad.any() else raw), int(bad.sum())


def _stale_rows(raw):
    keys = [k for k in ("q", "dq", "tau_J") if k in raw] + ([] if "tau_J" in raw else ["tau_ext"])
    same = np.ones(len(raw["t"]) - 1, bool) if len(raw["t"]) else np.zeros(0, bool)
    for k in keys:
        same &= np.all(raw[k][1:] == raw[k][:-1], axis=1)
    return np.concatenate([[False], same]) if len(raw["t"]) else same


def _interp(grid, t, v):
    """Linear interpolation of the columns of v (T, n) from stamps t onto grid (G,)."""
    return np.stack([np.interp(grid, t, v[:, j]) for j in range(v.shape[1])], axis=1)


# --- writing -----------------------------------------------------------------------------------------
def write_npz(path, log) -> None:
    """Write a log (a Log or a dict of arrays t, q, dq, [ddq], tau_J, tau_ext) as .npz, tau_ext in the paper's sign."""
    d = dataclasses.asdict(log) if isinstance(log, Log) else dict(log)
    arrays = {k: np.asarray(d[k]) for k in ("t", "q", "dq", "ddq", "tau_J", "tau_ext") if d.get(k) is not None}
    np.savez(path, **arrays, tau_ext_sign="paper")


def write_csv(path, log, with_ddq: bool = False) -> None:
    """Write a log as libfranka-style CSV: time, q[i], dq[i], tau_J[i], tau_ext_hat_filtered[i] (= -tau_ext, libfranka
    sign) and, if with_ddq, ddq[i]. Values are written with 17 significant digits, so reading loses nothing."""
    d = dataclasses.asdict(log) if isinstance(log, Log) else dict(log)
    n = np.asarray(d["q"]).shape[1]
    cols, names = [np.asarray(d["t"])[:, None]], ["time"]
    for key, sign, out in (("q", 1, "q"), ("dq", 1, "dq"), ("tau_J", 1, "tau_J"),
                           ("tau_ext", -1, "tau_ext_hat_filtered"), ("ddq", 1, "ddq")):
        if d.get(key) is None or (key == "ddq" and not with_ddq):
            continue
        cols.append(sign * np.asarray(d[key]))
        names += [f"{out}[{i}]" for i in range(n)]
    np.savetxt(path, np.hstack(cols), delimiter=",", header=",".join(names), comments="", fmt="%.17g")
