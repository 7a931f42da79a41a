"""Tests of the log reader on files written as the tools write them: libfranka's logger (franka::logToCSV, src/log.cpp),
a lab logger's `duration` CSV, plain CSV and .npz; checked against a closed-form signal sampled at the file's stamps."""
import warnings

import numpy as np
import pytest

from diagnosis.logs import LogConfig, load_log

N = 7
W = 2 * np.pi * np.linspace(0.1, 0.4, N)                    # rad/s, slow joint motion
Q0 = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.9, 0.8])        # rad, a pose inside the Panda's limits


def truth(t):
    """Closed-form q, dq, tau_J, tau_ext (paper sign) (T, 7) at times t (T,) [s]; model = 5 sin(q) stands in for the
    robot's model, so libfranka's tau_ext_hat_filtered = tau_J - model and the paper's tau_ext = model - tau_J."""
    q = Q0 + 0.3 * np.sin(W * t[:, None])
    dq = 0.3 * W * np.cos(W * t[:, None])
    tau_ext = 0.5 + 0.2 * np.cos(W * t[:, None])             # Nm, a load-like external torque, paper sign
    tau_J = 5 * np.sin(q) - tau_ext
    return q, dq, tau_J, tau_ext


def stamps_ms(rng, seconds=2.0, start=0):
    """Integer ms stamps of a 1 kHz log with dropped packets (2-3 ms steps) and one 8 ms hole, as a Panda logs."""
    t = start + np.arange(int(seconds * 1000))
    keep = rng.random(len(t)) > 0.03
    keep[[0, -1]] = True
    keep[700:707] = False                                   # an 8 ms step from 699 to 707
    return t[keep]


def fmt(v):
    """A double as a C++ ostream writes it by default (6 significant digits, %g)."""
    return f"{float(v):g}"


def write_libfranka(path, t_ms, rng):
    """A CSV exactly as libfranka's logToCSV writes it (src/log.cpp): header from csvName (", " inside a vector, ","
    between fields), then per record time.toMSec(), success_rate, state q, q_d, dq, dq_d, tau_J,
    tau_ext_hat_filtered, and the command q_d, dq_d, O_T_EE_d (16), O_dP_EE_d (6), tau_J_d."""
    def name(field, k):
        return ", ".join(f"{field}[{i}]" for i in range(k))
    header = ("time, success_rate, " + ",".join(name(f"state.{f}", N) for f in ("q", "q_d", "dq", "dq_d", "tau_J",
              "tau_ext_hat_filtered")) + "," + ",".join([name("cmd.q_d", N), name("cmd.dq_d", N),
              name("cmd.O_T_EE_d", 16), name("cmd.O_dP_EE_d", 6), name("cmd.tau_J_d", N)]))
    q, dq, tau_J, tau_ext = truth(t_ms / 1000.0)
    lines = [header]
    for k, ms in enumerate(t_ms):
        fields = [q[k], q[k] + 0.1, dq[k], dq[k] - 0.2, tau_J[k], -tau_ext[k],    # desired values differ from q, dq
                  q[k] - 0.05, dq[k] + 0.3, rng.normal(size=16), rng.normal(size=6), tau_J[k] + 1.0]
        lines.append(f"{int(ms)},{fmt(0.98)}," + ",".join(",".join(fmt(v) for v in a) for a in fields))
    path.write_text("\n".join(lines) + "\n")


def write_lab(path, t_ms, first_row="0,0.1,0.2"):
    """A lab logger's CSV: `duration` in ms since the start, q[i], dq[i], tau_J[i], tau_ext_hat_filtered[i], and a
    malformed first row (a partial line written as the logger started)."""
    q, dq, tau_J, tau_ext = truth(t_ms / 1000.0)
    header = ["duration"] + [f"{k}[{i}]" for k in ("q", "dq", "tau_J", "tau_ext_hat_filtered") for i in range(N)]
    body = np.hstack([t_ms[:, None], q, dq, tau_J, -tau_ext])
    rows = [",".join(repr(float(v)) for v in row) for row in body]
    path.write_text(",".join(header) + "\n" + first_row + "\n" + "\n".join(rows) + "\n")


def write_plain(path, t, time_name="t"):
    """A CSV with time in s under time_name and q_i style names, tau_ext in the paper's sign."""
    q, dq, tau_J, tau_ext = truth(t)
    header = [time_name] + [f"{k}_{i}" for k in ("q", "dq", "tau_J", "tau_ext") for i in range(N)]
    body = np.hstack([t[:, None], q, dq, tau_J, tau_ext])
    np.savetxt(path, body, delimiter=",", header=",".join(header), comments="", fmt="%.17g")


def write_npz(path, t):
    q, dq, tau_J, tau_ext = truth(t)
    np.savez(path, t=t, q=q, dq=dq, tau_J=tau_J, tau_ext=-tau_ext, tau_ext_sign="libfranka")


def assert_matches_truth(log, atol_q=3e-5, atol_dq=1e-4, atol_tau=2e-4):
    q, dq, tau_J, tau_ext = truth(log.t)
    np.testing.assert_allclose(log.q, q, rtol=0, atol=atol_q)
    np.testing.assert_allclose(log.dq, dq, rtol=0, atol=atol_dq)
    np.testing.assert_allclose(log.tau_J, tau_J, rtol=0, atol=atol_tau)
    np.testing.assert_allclose(log.tau_ext, tau_ext, rtol=0, atol=atol_tau)      # paper sign
    np.testing.assert_allclose(log.tau_ext, 5 * np.sin(log.q) - log.tau_J, rtol=0, atol=5 * atol_tau)   # Eq. 1


# --- 1. libfranka's logger ---------------------------------------------------------------------------------------
def test_libfranka_logger_csv_reads_time_in_ms_state_columns_and_flips_tau_ext(tmp_path):
    rng = np.random.default_rng(0)
    t_ms = stamps_ms(rng, start=3_600_123)                  # robot clock: ms since the controller started
    write_libfranka(tmp_path / "franka.csv", t_ms, rng)
    log = load_log(tmp_path / "franka.csv")
    assert log.info["format"] == "libfranka logger" and log.info["time_column"] == "time [ms]"
    assert log.t[0] == pytest.approx(3600.123, abs=1e-9) and log.info["dt"] == pytest.approx(1e-3, abs=1e-12)
    assert len(log) == 2000 and log.info["resampled"]        # dropped packets and the 8 ms hole filled in
    assert log.info["bad_rows"] == 0
    assert_matches_truth(log)                                 # q, not state.q_d or cmd.q_d; tau_ext = -filtered


def test_libfranka_logger_csv_with_stale_repeats_drops_them(tmp_path):
    rng = np.random.default_rng(1)
    write_libfranka(tmp_path / "franka.csv", stamps_ms(rng), rng)
    lines = (tmp_path / "franka.csv").read_text().splitlines()
    stale = [100, 101, 500, 1200]
    for i in stale:                                           # a repeated packet: new time stamp, old values
        lines[i + 1] = lines[i + 1].split(",", 1)[0] + "," + lines[i].split(",", 1)[1]
    (tmp_path / "franka.csv").write_text("\n".join(lines) + "\n")
    log = load_log(tmp_path / "franka.csv")
    assert log.info["stale_rows"] == len(stale)
    assert_matches_truth(log)


# --- 2. a lab logger: duration in ms and malformed rows ----------------------------------------------------------
def test_lab_logger_duration_csv_drops_and_reports_malformed_rows(tmp_path):
    rng = np.random.default_rng(2)
    t_ms = stamps_ms(rng)                                     # ms since the start, from 0
    t_ms = t_ms + np.concatenate([[0], rng.uniform(-0.2, 0.2, len(t_ms) - 1)])   # uneven stamps
    write_lab(tmp_path / "lab.csv", t_ms)
    lines = (tmp_path / "lab.csv").read_text().splitlines()
    cells = lines[900].split(",")
    cells[3] = "ovf"                                          # a non-number in one field of line 901
    lines[900] = ",".join(cells)
    (tmp_path / "lab.csv").write_text("\n".join(lines) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")                        # reported in info, not by a library warning
        log = load_log(tmp_path / "lab.csv")
    assert log.info["bad_rows"] == 2 and log.info["bad_lines"] == [2, 901]
    assert log.info["time_column"] == "duration [ms]" and log.t[0] == 0.0
    assert log.info["rows"] == len(t_ms) - 1                  # all the good rows, less the ovf one
    assert_matches_truth(log)


def test_more_malformed_rows_than_max_bad_rows_is_refused(tmp_path):
    rng = np.random.default_rng(3)
    t_ms = stamps_ms(rng)
    write_lab(tmp_path / "lab.csv", t_ms)
    with pytest.raises(ValueError, match=r"csv: 1 of \d+ data rows .* malformed \(first at line 2: 3 fields, "
                                         r"expected 29.*max_bad_rows = 0\b"):
        load_log(tmp_path / "lab.csv", LogConfig(max_bad_rows=0))
    text = (tmp_path / "lab.csv").read_text().splitlines()
    decimal_comma = [text[0]] + [line.replace(".", ",") for line in text[2:]]   # a locale writing 0,5 for 0.5
    (tmp_path / "comma.csv").write_text("\n".join(decimal_comma) + "\n")
    with pytest.raises(ValueError, match=r"csv: (\d+) of \1 data rows .* malformed .*decimal mark"):
        load_log(tmp_path / "comma.csv")


# --- 3. time gaps ------------------------------------------------------------------------------------------------
def test_a_gap_longer_than_max_gap_is_refused_naming_where_and_how_long(tmp_path):
    t = 1e-3 * np.arange(2000)
    t[1000:] += 100.0                                         # the logger paused for 100 s
    write_plain(tmp_path / "gap.csv", t)
    write_npz(tmp_path / "gap.npz", t)
    for name in ("gap.csv", "gap.npz"):
        with pytest.raises(ValueError, match=r"t: expected no gap longer than config.max_gap = 0.05 s, found 1, "
                                             r"the first of 100.001 s from t = 0.999 s to 101 s"):
            load_log(tmp_path / name)


def test_a_gap_within_max_gap_is_interpolated(tmp_path):
    t = 1e-3 * np.arange(2000)
    t[1000:] += 0.3                                           # 301 ms
    write_plain(tmp_path / "gap.csv", t)
    with pytest.raises(ValueError, match="max_gap = 0.05 s"):
        load_log(tmp_path / "gap.csv")
    log = load_log(tmp_path / "gap.csv", LogConfig(max_gap=0.5))
    assert len(log) == 2300 and log.info["resampled"]
    q, _, _, _ = truth(log.t)
    inside = (log.t > 1.0) & (log.t < 1.3)
    chord = np.stack([np.interp(log.t[inside], t, truth(t)[0][:, j]) for j in range(N)], axis=1)
    np.testing.assert_allclose(log.q[inside], chord, rtol=0, atol=1e-9)          # linear over the gap
    np.testing.assert_allclose(log.q[~inside], q[~inside], rtol=0, atol=1e-12)   # measured samples kept


def test_time_in_ms_under_a_seconds_column_is_refused_with_a_unit_hint(tmp_path):
    write_plain(tmp_path / "ms.csv", 1e-3 * np.arange(2000), time_name="time")
    text = (tmp_path / "ms.csv").read_text().splitlines()
    rows = [str(k) + line[line.index(","):] for k, line in enumerate(text[1:])]   # time in ms, read as s
    (tmp_path / "ms.csv").write_text("\n".join([text[0]] + rows) + "\n")
    with pytest.raises(ValueError, match=r"median step of 1 s \(time stamps in ms read as s\?\)"):
        load_log(tmp_path / "ms.csv")


# --- 4. paths that are not files ---------------------------------------------------------------------------------
def test_a_path_that_is_not_a_readable_log_raises_value_error_naming_path(tmp_path):
    for bad in (None, 3):
        with pytest.raises(ValueError, match=rf"path: expected a log file path .*found {type(bad).__name__}"):
            load_log(bad)
    (tmp_path / "binary.csv").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00\x01" * 10)
    with pytest.raises(ValueError, match=r"path: could not read the log .*binary.csv.* as CSV text"):
        load_log(tmp_path / "binary.csv")


def test_a_column_named_twice_is_refused(tmp_path):
    write_plain(tmp_path / "twice.csv", 1e-3 * np.arange(500))
    text = (tmp_path / "twice.csv").read_text().replace("q_0,", "state.q[0],", 1).replace("q_1,", "q[0],", 1)
    (tmp_path / "twice.csv").write_text(text)
    with pytest.raises(ValueError, match=r"csv: expected each column once, found 'q\[0\]' in columns 1 and 2"):
        load_log(tmp_path / "twice.csv")


# --- 5. every format reads the same signal -----------------------------------------------------------------------
@pytest.mark.parametrize("fmt_name", ["npz", "plain csv", "libfranka csv", "lab csv"])
def test_every_format_loads_the_closed_form_signal(tmp_path, fmt_name):
    rng = np.random.default_rng(4)
    t_ms = stamps_ms(rng)
    path = tmp_path / ("log.npz" if fmt_name == "npz" else "log.csv")
    if fmt_name == "npz":
        write_npz(path, t_ms / 1000.0)
    elif fmt_name == "plain csv":
        write_plain(path, t_ms / 1000.0)
    elif fmt_name == "libfranka csv":
        write_libfranka(path, t_ms, rng)
    else:
        write_lab(path, t_ms)
    log = load_log(path)
    assert log.t[0] == 0.0 and len(log) == 2000 and log.info["dt"] == pytest.approx(1e-3, abs=1e-12)
    assert log.info["bad_rows"] == (1 if fmt_name == "lab csv" else 0)
    assert_matches_truth(log)


# --- 4. what a file holds: byte-order mark, complex and impossible values, what was dropped and filled in ---------
def test_a_csv_with_a_byte_order_mark_loads_like_one_without(tmp_path):
    t = 1e-3 * np.arange(1000)
    write_plain(tmp_path / "plain.csv", t)
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + (tmp_path / "plain.csv").read_bytes())   # a spreadsheet's
    a, b = load_log(tmp_path / "plain.csv"), load_log(tmp_path / "bom.csv")
    for key in ("t", "q", "dq", "tau_J", "tau_ext"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))


def test_complex_bool_and_impossible_values_are_refused_naming_the_field(tmp_path):
    t = 1e-3 * np.arange(1000)
    q, dq, tau_J, tau_ext = truth(t)
    good = dict(t=t, q=q, dq=dq, tau_J=tau_J, tau_ext=tau_ext)
    cases = {"q": (q + 0j, r"q: expected real numbers.*complex"),
             "dq": (dq > 0, r"dq: expected real numbers.*bool"),
             "tau_J": (np.where(t[:, None] > 0.5, 1e300, tau_J), r"tau_J: expected \|tau_J\| <= 1000 Nm, found 1e\+300"),
             "tau_ext": (tau_ext * 1e6, r"tau_ext: expected \|tau_ext\| <= 1000 Nm")}
    for key, (bad, message) in cases.items():
        np.savez(tmp_path / "bad.npz", **dict(good, **{key: bad}))
        with pytest.raises(ValueError, match=message):
            load_log(tmp_path / "bad.npz")
    np.savez(tmp_path / "deg.npz", **dict(good, q=np.degrees(q)))         # degrees where radians belong
    with pytest.raises(ValueError, match=r"q: expected \|q\| <= 12.5664 rad"):
        load_log(tmp_path / "deg.npz")


def test_missing_cycles_and_malformed_rows_are_counted_and_said(tmp_path, capsys):
    from diagnosis.diagnose import main
    from diagnosis.report import cleaning_summary
    t = 1e-3 * np.arange(4000)
    keep = np.ones(len(t), bool)
    keep[2000:2040] = False                                   # 40 missing 1 kHz cycles: a 41 ms gap
    write_lab(tmp_path / "lab.csv", 1e3 * t[keep])            # and one malformed first row (file line 2)
    log = load_log(tmp_path / "lab.csv")
    assert (log.info["gaps"], log.info["missing_cycles"], log.info["bad_rows"]) == (1, 40, 1)
    text = cleaning_summary(log.info)
    assert "1 malformed (file lines 2)" in text and "40 missing cycles in 1 gaps" in text, text
    assert "longest 41 ms at t = 1.999 s" in text and "missing cycles filled in by linear interpolation" in text, text
