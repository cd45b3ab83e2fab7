"""Tests for physics.recording: parsing, error reporting and the format/parse round trip."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from physics.recording import (
    Recording,
    RecordingError,
    file_row,
    format_recording,
    parse_recording,
)

HEADER = "t,step,psi_t,theta_t,phi_t,mx,my,mz,ax,ay,az,temp_c"

MINIMAL = """\
# compasscal-recording: 1
# serial: SN-0001
# station: lab-1
t,step,psi_t,theta_t,phi_t,mx,my,mz,ax,ay,az,temp_c
0.000,level,0.000,0.000,0.000,3614.2,-412.7,2746.9,12.1,-3.0,-16385.2,
0.050,level,0.000,0.000,0.000,3615.0,-411.9,2747.1,12.3,-2.8,-16384.9,23.5
0.100,sweep_z,10.0,0.000,0.000,3500.0,-300.0,2740.0,12.0,-3.1,-16385.0,23.6
"""

ROW = "0.0,level,0,0,0,1,2,3"  # a good row for the required columns only
REQ = "t,step,psi_t,theta_t,phi_t,mx,my,mz"


def test_minimal_file_values_and_types() -> None:
    rec = parse_recording(MINIMAL)
    assert len(rec) == 3
    np.testing.assert_array_equal(rec.t, [0.0, 0.05, 0.1])
    assert rec.t.dtype == np.float64
    assert rec.step.dtype == object
    assert rec.step.tolist() == ["level", "level", "sweep_z"]
    np.testing.assert_array_equal(rec.psi_t, [0.0, 0.0, 10.0])
    assert rec.mag.shape == (3, 3)
    np.testing.assert_array_equal(rec.mag[0], [3614.2, -412.7, 2746.9])
    assert rec.acc is not None and rec.acc.shape == (3, 3)
    np.testing.assert_array_equal(rec.acc[2], [12.0, -3.1, -16385.0])
    # temp_c empty on the first row only -> NaN there, values elsewhere
    assert rec.temp_c is not None
    assert math.isnan(rec.temp_c[0])
    np.testing.assert_array_equal(rec.temp_c[1:], [23.5, 23.6])
    assert rec.serial == "SN-0001"
    assert rec.extra == {}


def test_metadata_parsing() -> None:
    text = (
        "#compasscal-recording:1\n"
        "#   serial :  SN-42  \n"
        "# just a comment without colon\n"
        "\n"
        "# url: http://x:8080/a\n"
        "# temperature_c: 23.5\n"
        f"{REQ}\n{ROW}\n"
    )
    rec = parse_recording(text)
    assert rec.meta == {
        "compasscal-recording": "1",
        "serial": "SN-42",
        "url": "http://x:8080/a",  # split on the first colon only
        "temperature_c": "23.5",
    }
    assert list(rec.meta) == ["compasscal-recording", "serial", "url", "temperature_c"]
    assert rec.serial == "SN-42"


def test_no_serial_is_none() -> None:
    assert parse_recording(f"{REQ}\n{ROW}\n").serial is None


def test_columns_in_other_order_with_extra_columns() -> None:
    text = (
        'note,mz,my,mx,phi_t,theta_t,psi_t,step, t ,rig\n'
        '" a, b ",3,2,1,30,20,10,"sweep, x",0.5,R1\n'
        ',6,5,4,31,21,11,level,0.6, R2\n'
    )
    rec = parse_recording(text)
    np.testing.assert_array_equal(rec.t, [0.5, 0.6])
    assert rec.step.tolist() == ["sweep, x", "level"]
    np.testing.assert_array_equal(rec.mag, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(rec.psi_t, [10, 11])
    np.testing.assert_array_equal(rec.theta_t, [20, 21])
    np.testing.assert_array_equal(rec.phi_t, [30, 31])
    assert rec.acc is None and rec.temp_c is None
    # extras kept verbatim, as strings, in file order
    assert list(rec.extra) == ["note", "rig"]
    assert rec.extra["note"] == [" a, b ", ""]
    assert rec.extra["rig"] == ["R1", " R2"]


def test_acc_and_temp_absent() -> None:
    rec = parse_recording(f"{REQ}\n{ROW}\n")
    assert rec.acc is None
    assert rec.temp_c is None


def test_acc_and_temp_present_but_empty_everywhere() -> None:
    text = f"{HEADER}\n0,level,0,0,0,1,2,3,,,,\n1,level,0,0,0,1,2,3, , , ,\n"
    rec = parse_recording(text)
    assert rec.acc is None
    assert rec.temp_c is None


def test_acc_and_temp_partially_empty_are_nan() -> None:
    text = f"{HEADER}\n0,level,0,0,0,1,2,3,,,,\n1,level,0,0,0,1,2,3,7,8,9,21.5\n2,level,0,0,0,1,2,3,10,,12,\n"
    rec = parse_recording(text)
    assert rec.acc is not None and rec.temp_c is not None
    assert np.isnan(rec.acc[0]).all()
    np.testing.assert_array_equal(rec.acc[1], [7, 8, 9])
    assert rec.acc[2, 0] == 10 and math.isnan(rec.acc[2, 1]) and rec.acc[2, 2] == 12
    assert math.isnan(rec.temp_c[0]) and rec.temp_c[1] == 21.5 and math.isnan(rec.temp_c[2])


def test_duplicate_column_named() -> None:
    with pytest.raises(RecordingError, match=r"duplicate column\(s\): mx") as exc:
        parse_recording(f"t,step,psi_t,theta_t,phi_t,mx,my,mz, mx\n{ROW},1\n")
    assert "line 1" in str(exc.value)


def test_missing_required_columns_all_listed() -> None:
    with pytest.raises(RecordingError) as exc:
        parse_recording("# serial: x\nt,step,psi_t,mx,foo\n0,level,0,1,2\n")
    msg = str(exc.value)
    assert "line 2" in msg
    for col in ("theta_t", "phi_t", "my", "mz"):
        assert col in msg
    assert "missing required column(s): theta_t, phi_t, my, mz" in msg


def test_column_names_are_case_sensitive() -> None:
    with pytest.raises(RecordingError, match="missing required column.*: t$"):
        parse_recording(f"T,step,psi_t,theta_t,phi_t,mx,my,mz\n{ROW}\n")


@pytest.mark.parametrize(
    ("cols", "missing"),
    [("ax", "ay, az"), ("ax,az", "ay"), ("ay,az", "ax")],
)
def test_only_some_acc_columns_is_error(cols: str, missing: str) -> None:
    n_extra = cols.count(",") + 1
    with pytest.raises(RecordingError) as exc:
        parse_recording(f"{REQ},{cols}\n{ROW}{',1' * n_extra}\n")
    assert f"missing: {missing}" in str(exc.value)


def test_no_column_line() -> None:
    with pytest.raises(RecordingError, match="no column line"):
        parse_recording("# serial: x\n\n# only comments\n")


def test_no_data_rows() -> None:
    with pytest.raises(RecordingError, match="^recording has no data rows$"):
        parse_recording(f"# serial: x\n{HEADER}\n\n")


def test_malformed_rows_reported_with_line_numbers() -> None:
    text = "\n".join([
        "# compasscal-recording: 1",              # 1
        HEADER,                                   # 2
        "0.0,level,0,0,0,1,2,3,4,5,6,20",         # 3 ok
        "0.1,level,0,0,0,1,2,3,4,5,6",            # 4 wrong field count
        "0.2,level,0,0,0,abc,2,3,4,5,6,20",       # 5 bad float in mx
        "",                                       # 6 blank (ignored, but counted)
        "0.3,level,0,nan,0,1,2,3,4,5,6,20",       # 7 nan in theta_t
        "0.4,level,0,0,0,1,2,3,4,inf,6,20",       # 8 inf in optional ay
        "0.5,level,0,0,0,1,,3,4,5,6,-inf",        # 9 empty my + -inf temp_c
        "0.6,,0,0,0,1,2,3,4,5,6,20",              # 10 empty step
        "0.7,level,0,0,0,1,2,3,4,5,6,20",         # 11 ok
        "0.65,level,0,0,0,1,2,3,4,5,6,20",        # 12 time goes backwards
        "0.8,level,0,0,0,1,2,3,4,5,6,20",         # 13 ok
    ]) + "\n"
    with pytest.raises(RecordingError) as exc:
        parse_recording(text)
    msg = str(exc.value)
    assert msg.startswith("7 malformed row(s)")
    assert re.search(r"line 4: expected 12 fields, got 11", msg)
    assert "line 5: column mx: not a number ('abc')" in msg
    assert "line 7: column theta_t: non-finite value ('nan')" in msg
    assert "line 8: column ay: non-finite value ('inf')" in msg
    assert "line 9: column my: empty required cell" in msg
    assert "line 9: column temp_c: non-finite value ('-inf')" in msg
    assert "line 10: column step: empty required cell" in msg
    assert re.search(r"line 12: column t: time goes backwards.*line 11", msg)
    reported = {int(n) for n in re.findall(r"line (\d+):", msg)}
    assert reported == {4, 5, 7, 8, 9, 10, 12}


def test_equal_times_are_allowed() -> None:
    rec = parse_recording(f"{REQ}\n1.0,a,0,0,0,1,2,3\n1.0,b,0,0,0,1,2,3\n")
    assert rec.step.tolist() == ["a", "b"]


def test_bad_quoting_is_malformed_row() -> None:
    with pytest.raises(RecordingError, match=r"^1 malformed row\(s\):\nline 3: bad CSV quoting"):
        parse_recording(f"{REQ}\n{ROW}\n1.0,\"level,0,0,0,1,2,3\n")


def test_underscore_number_rejected() -> None:
    with pytest.raises(RecordingError, match=r"line 2: column mx: not a number \('1_000'\)"):
        parse_recording(f"{REQ}\n0,level,0,0,0,1_000,2,3\n")


def test_problem_list_is_truncated_after_20() -> None:
    rows = [f"{i},level,0,0,0,x,2,3" for i in range(25)]
    with pytest.raises(RecordingError) as exc:
        parse_recording(REQ + "\n" + "\n".join(rows) + "\n")
    msg = str(exc.value)
    assert msg.startswith("25 malformed row(s)")
    assert msg.count("column mx: not a number") == 20
    assert "line 21:" in msg and "line 22:" not in msg
    assert msg.rstrip().endswith("... and 5 more")


def test_skip_bad_rows_drops_and_counts() -> None:
    text = f"{REQ}\n1,a,0,0,0,1,2,3\n1.5,b,0,0,0,x,2,3\n0.5,c,0,0,0,1,2,3\n2,d,0,0,0,1,2,3\n3,e,0,0\n"
    rec = parse_recording(text, skip_bad_rows=True)
    assert rec.step.tolist() == ["a", "d"]  # b: bad float, c: time goes backwards, e: field count
    np.testing.assert_array_equal(rec.t, [1.0, 2.0])
    np.testing.assert_array_equal(rec.mag, [[1, 2, 3], [1, 2, 3]])
    assert rec.meta["skipped_rows"] == "3"


def test_skip_bad_rows_time_compared_with_last_kept_row() -> None:
    # The bad row at t=5 is dropped for its float error, so t=2 is compared with t=1 and kept.
    text = f"{REQ}\n1,a,0,0,0,1,2,3\n5,b,0,0,0,x,2,3\n2,c,0,0,0,1,2,3\n"
    rec = parse_recording(text, skip_bad_rows=True)
    assert rec.step.tolist() == ["a", "c"]
    assert rec.meta["skipped_rows"] == "1"


def test_skip_bad_rows_clean_file_reports_zero() -> None:
    rec = parse_recording(f"{REQ}\n{ROW}\n", skip_bad_rows=True)
    assert rec.meta["skipped_rows"] == "0"
    assert "skipped_rows" not in parse_recording(f"{REQ}\n{ROW}\n").meta


def test_skip_bad_rows_all_bad_still_raises() -> None:
    with pytest.raises(RecordingError, match=r"^recording has no data rows \(2 malformed"):
        parse_recording(f"{REQ}\n0,a,0,0,0,x,2,3\n1,b\n", skip_bad_rows=True)


def test_bom_and_crlf() -> None:
    text = "\ufeff" + MINIMAL.replace("\n", "\r\n")
    rec = parse_recording(text)
    ref = parse_recording(MINIMAL)
    assert list(rec.meta) == ["compasscal-recording", "serial", "station"]
    assert rec.meta == ref.meta
    np.testing.assert_array_equal(rec.t, ref.t)
    np.testing.assert_array_equal(rec.temp_c, ref.temp_c)  # last column has no stray "\r"
    assert rec.step.tolist() == ref.step.tolist()


def test_crlf_does_not_leak_into_verbatim_extra_column() -> None:
    rec = parse_recording(f"{REQ},rig\r\n{ROW},R1\r\n0.1,a,0,0,0,1,2,3,R2\r\n")
    assert rec.extra == {"rig": ["R1", "R2"]}


def test_bom_before_column_line_and_crlf_line_numbers() -> None:
    text = f"\ufeff{REQ}\r\n{ROW}\r\n0.1,level,0,0,0,bad,2,3\r\n"
    with pytest.raises(RecordingError, match=r"line 3: column mx: not a number \('bad'\)"):
        parse_recording(text)


def test_comment_lines_after_column_line_are_ignored_but_counted() -> None:
    text = f"{REQ}\n{ROW}\n# a note\n0.1,level,0,0,0,oops,2,3\n"
    with pytest.raises(RecordingError, match="line 4: column mx"):
        parse_recording(text)


def test_select_mask_index_slice() -> None:
    rec = parse_recording(MINIMAL.replace(HEADER, HEADER + ",rig").replace(",\n", ",,A\n")
                          .replace("23.5\n", "23.5,B\n").replace("23.6\n", "23.6,C\n"))
    assert rec.extra["rig"] == ["A", "B", "C"]
    sub = rec.select(np.array([True, False, True]))
    assert len(sub) == 2
    assert sub.step.tolist() == ["level", "sweep_z"]
    assert sub.extra["rig"] == ["A", "C"]
    assert sub.meta == rec.meta and sub.meta is not rec.meta
    np.testing.assert_array_equal(sub.mag, rec.mag[[0, 2]])
    assert sub.acc is not None and sub.acc.shape == (2, 3)
    one = rec.select(1)
    assert len(one) == 1 and one.t.tolist() == [0.05] and one.extra["rig"] == ["B"]
    assert rec.select(slice(1, None)).step.tolist() == ["level", "sweep_z"]
    assert rec.select([2, 0]).t.tolist() == [0.1, 0.0]
    no_acc = parse_recording(f"{REQ}\n{ROW}\n").select([0])
    assert no_acc.acc is None and no_acc.temp_c is None


def test_from_arrays_converts_and_validates() -> None:
    rec = Recording.from_arrays([0, 1], ["a", 2], [0, 0], [0, 0], [0, 0], [[1, 2, 3], [4, 5, 6]],
                                meta={"serial": "S"})
    assert rec.t.dtype == np.float64 and rec.mag.dtype == np.float64
    assert rec.step.dtype == object and rec.step.tolist() == ["a", "2"]
    assert rec.serial == "S"
    with pytest.raises(RecordingError, match=r"mag has shape \(2, 2\), expected \(2, 3\)"):
        Recording.from_arrays([0, 1], ["a", "b"], [0, 0], [0, 0], [0, 0], [[1, 2], [3, 4]])
    with pytest.raises(RecordingError, match="psi_t has shape"):
        Recording.from_arrays([0, 1], ["a", "b"], [0], [0, 0], [0, 0], np.zeros((2, 3)))
    with pytest.raises(RecordingError, match="step"):
        Recording.from_arrays([0, 1], "ab", [0, 0], [0, 0], [0, 0], np.zeros((2, 3)))
    with pytest.raises(RecordingError, match="t decreases at row 1"):
        Recording.from_arrays([1, 0], ["a", "b"], [0, 0], [0, 0], [0, 0], np.zeros((2, 3)))
    with pytest.raises(RecordingError, match="non-finite"):
        Recording.from_arrays([0, 1], ["a", "b"], [0, np.nan], [0, 0], [0, 0], np.zeros((2, 3)))
    all_nan = Recording.from_arrays([0], ["a"], [0], [0], [0], [[1, 2, 3]],
                                    acc=[[np.nan] * 3], temp_c=[np.nan])
    assert all_nan.acc is None and all_nan.temp_c is None


def test_format_layout() -> None:
    rec = Recording.from_arrays(
        [0, 0.0505], ["level", 'a "q", b'], [1.23456, 0], [0, 0], [0, -0.5], [[1.005, 2, 3], [4, 5, 6]],
        acc=[[1, 2, 3], [np.nan, 5, 6]], temp_c=[np.nan, 22.125],
        meta={"compasscal-recording": "9", "serial": "SN-1", "skipped_rows": "4"},
        extra={"rig": ["A", "B"]},
    )
    lines = format_recording(rec).splitlines()
    assert lines[0] == "# compasscal-recording: 1"
    assert lines[1] == "# serial: SN-1"
    assert lines[2] == HEADER + ",rig"
    # at least the usual decimals, and every digit a value has (an export is what was recorded)
    assert lines[3] == "0.000,level,1.23456,0.0000,0.0000,1.005,2.00,3.00,1.00,2.00,3.00,,A"
    assert lines[4] == '0.0505,"a ""q"", b",0.0000,0.0000,-0.5000,4.00,5.00,6.00,,5.00,6.00,22.125,B'
    assert len(lines) == 5


def test_format_without_acc_temp_writes_empty_cells() -> None:
    rec = parse_recording(f"{REQ}\n{ROW}\n")
    text = format_recording(rec)
    assert text.splitlines()[-1] == "0.000,level,0.0000,0.0000,0.0000,1.00,2.00,3.00,,,,"
    back = parse_recording(text)
    assert back.acc is None and back.temp_c is None


def test_format_refuses_unreadable_recordings() -> None:
    rec = parse_recording(f"{REQ}\n{ROW}\n")
    rec.step = np.array(["two\nlines"], dtype=object)
    with pytest.raises(RecordingError, match="line break"):
        format_recording(rec)
    rec.step = np.array(["ok"], dtype=object)
    rec.meta = {"bad:key": "v"}
    with pytest.raises(RecordingError, match="metadata key"):
        format_recording(rec)


# --- round trip -------------------------------------------------------------------------------

_NO_BREAKS = st.characters(blacklist_categories=("Cs",), blacklist_characters="\r\n")
_label = st.text(_NO_BREAKS, min_size=1, max_size=12).map(str.strip).filter(bool)
_meta_key = (st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\r\n:"),
                     min_size=1, max_size=10)
             .map(str.strip).filter(lambda k: k and k not in ("compasscal-recording", "skipped_rows")))
_meta_value = st.text(_NO_BREAKS, max_size=15).map(str.strip)
_KNOWN = set(HEADER.split(","))


def _finite(bound: float) -> st.SearchStrategy[float]:
    return st.floats(-bound, bound, allow_nan=False, allow_infinity=False)


def _maybe_nan(bound: float) -> st.SearchStrategy[float]:
    return st.one_of(st.just(math.nan), _finite(bound))


@st.composite
def recordings(draw: st.DrawFn) -> Recording:
    n = draw(st.integers(1, 15))
    t = sorted(draw(st.lists(st.floats(0, 1e5), min_size=n, max_size=n)))
    angles = [draw(st.lists(_finite(720), min_size=n, max_size=n)) for _ in range(3)]
    mag = draw(st.lists(st.lists(_finite(1e5), min_size=3, max_size=3), min_size=n, max_size=n))
    acc = draw(st.none() | st.lists(st.lists(_maybe_nan(4e4), min_size=3, max_size=3), min_size=n, max_size=n))
    temp = draw(st.none() | st.lists(_maybe_nan(150), min_size=n, max_size=n))
    meta = draw(st.dictionaries(_meta_key, _meta_value, max_size=4))
    extra_names = draw(st.lists(_label.filter(lambda s: s not in _KNOWN), max_size=2, unique=True))
    extra = {name: draw(st.lists(st.text(_NO_BREAKS, max_size=8), min_size=n, max_size=n))
             for name in extra_names}
    steps = draw(st.lists(_label, min_size=n, max_size=n))
    return Recording.from_arrays(t, steps, *angles, mag, acc=acc, temp_c=temp, meta=meta, extra=extra)


def _close(actual: np.ndarray | None, expected: np.ndarray | None, decimals: int) -> None:
    assert (actual is None) == (expected is None)
    if expected is None:
        return
    assert actual is not None and actual.shape == expected.shape
    np.testing.assert_array_equal(np.isnan(actual), np.isnan(expected))
    ok = ~np.isnan(expected)
    # half a unit in the last printed place, plus float noise for large values
    tol = 0.5 * 10.0 ** -decimals + 1e-12 * np.abs(expected[ok])
    assert np.all(np.abs(actual[ok] - expected[ok]) <= tol)


@settings(max_examples=200, deadline=None)
@given(recordings())
def test_round_trip(rec: Recording) -> None:
    text = format_recording(rec)
    back = parse_recording(text)
    assert len(back) == len(rec)
    assert back.step.tolist() == rec.step.tolist()
    _close(back.t, rec.t, 3)
    for name in ("psi_t", "theta_t", "phi_t"):
        _close(getattr(back, name), getattr(rec, name), 4)
    _close(back.mag, rec.mag, 2)
    _close(back.acc, rec.acc, 2)
    _close(back.temp_c, rec.temp_c, 2)
    assert back.meta == {"compasscal-recording": "1", **rec.meta}
    assert back.extra == rec.extra
    # once rounded, formatting is a fixed point
    assert format_recording(back) == text


def test_a_recordings_fingerprint_survives_its_file_and_changes_with_a_reading() -> None:
    """The analyser seeds its nulls with the fingerprint: an export read back, or the same numbers to the
    file's decimals, give the same one; one reading one count off, another time base, other angles or a
    temperature column added give another."""
    rng = np.random.default_rng(3)
    n = 50
    rec = Recording.from_arrays(np.arange(n) * 0.05, ["hold"] * n, rng.uniform(-180, 180, n), rng.uniform(-90, 90, n),
                                rng.uniform(-180, 180, n), rng.integers(-3000, 3000, (n, 3)),
                                acc=rng.integers(-1000, 1000, (n, 3)))
    fp = rec.fingerprint()
    assert 0 <= fp < 2 ** 53  # exact as a JSON number
    assert parse_recording(format_recording(rec)).fingerprint() == fp
    noisy = rec.select(slice(None))
    noisy.t = noisy.t + 1e-9  # float noise far below the millisecond the file keeps
    noisy.mag = noisy.mag * (1 + 1e-13)
    assert noisy.fingerprint() == fp
    changed = [rec.select(slice(None)) for _ in range(4)]
    changed[0].mag[7, 1] += 1
    changed[1].t = changed[1].t * 1.01
    changed[2].phi_t[3] += 0.01
    changed[3].temp_c = np.full(n, 25.0)
    assert len({fp, *(c.fingerprint() for c in changed)}) == 5


def test_one_time_stamp_ahead_of_both_neighbours_is_the_bad_row() -> None:
    """A row whose t jumps ahead (1000 among 1, 2, 3, ...) is the one named, not every row after it (which
    made --skip-bad-rows throw away the rest of the recording); a row that goes back stays the one named."""
    rows = [f"{t},s{t},0,0,0,1,2,3" for t in range(1, 9)]
    rows[3] = "1000,jump,0,0,0,1,2,3"  # data row 3
    text = REQ + "\n" + "\n".join(rows) + "\n"
    with pytest.raises(RecordingError) as err:
        parse_recording(text)
    msg = str(err.value)
    assert msg.startswith("1 malformed row(s)") and "line 5: column t: 1000 is ahead of the rows before and after it" in msg
    rec = parse_recording(text, skip_bad_rows=True)
    assert len(rec) == 7 and "jump" not in rec.step.tolist() and rec.meta["skipped_at_rows"] == "3"
    assert [file_row(rec, i) for i in (2, 3)] == [2, 4]


def test_a_first_time_stamp_ahead_of_the_rest_is_the_bad_row() -> None:
    """The first row's t far ahead (1e300 before 0.05, 0.10, ...): that row is named, not every other row
    (the rule for a jump needed two rows before it, and --skip-bad-rows kept the one bad row alone). With
    only two rows nothing says which is wrong, and the second stays the one named."""
    rows = ["1e300,first,0,0,0,1,2,3", *(f"{0.05 * k:.2f},s,0,0,0,1,2,3" for k in range(1, 8))]
    text = REQ + "\n" + "\n".join(rows) + "\n"
    with pytest.raises(RecordingError) as err:
        parse_recording(text)
    msg = str(err.value)
    assert msg.startswith("1 malformed row(s)") and "line 2: column t: 1e300 is ahead of the rows after it" in msg, msg
    rec = parse_recording(text, skip_bad_rows=True)
    assert np.allclose(rec.t, [0.05 * k for k in range(1, 8)]) and rec.meta["skipped_at_rows"] == "0"
    assert [file_row(rec, i) for i in (0, 6)] == [1, 7]
    with pytest.raises(RecordingError, match="line 3: column t: time goes backwards"):
        parse_recording(REQ + "\n5,a,0,0,0,1,2,3\n1,b,0,0,0,1,2,3\n")


@pytest.mark.parametrize("factor, unit", [(1e3, "milliseconds"), (1e6, "microseconds")])
def test_a_time_column_the_files_own_rate_contradicts_is_refused(factor: float, unit: str) -> None:
    """t in milliseconds under '# sample_rate_hz: 20' (samples 50 "s" apart where the file says 0.05 s):
    refused naming the likely unit. Read as seconds it made a two-minute log last days, without a word.
    Without a rate line, or with samples spaced as it says (gaps between holds too), it is read as is."""
    rows = "".join(f"{factor * (k * 0.05 + 10 * (k // 20)):.6g},s,0,0,0,1,2,3\n" for k in range(60))
    with pytest.raises(RecordingError, match=f"column t: consecutive samples are 50 s apart .* looks like {unit}") \
            if factor == 1e3 else pytest.raises(RecordingError, match=f"looks like {unit}"):
        parse_recording("# sample_rate_hz: 20\n" + REQ + "\n" + rows)
    assert len(parse_recording(REQ + "\n" + rows)) == 60
    seconds = "".join(f"{k * 0.05 + 10 * (k // 20):.6g},s,0,0,0,1,2,3\n" for k in range(60))
    assert len(parse_recording("# sample_rate_hz: 20\n" + REQ + "\n" + seconds)) == 60


def test_a_later_format_version_is_refused() -> None:
    """'# compasscal-recording: 2' may give a column another meaning: named, not read as format 1."""
    with pytest.raises(RecordingError, match="'# compasscal-recording: 2': this compasscal reads format 1"):
        parse_recording(MINIMAL.replace("compasscal-recording: 1", "compasscal-recording: 2"))
    assert len(parse_recording(MINIMAL.replace("compasscal-recording: 1", "compasscal-recording: 1.0"))) == 3


def test_a_row_missing_a_table_angle_is_a_bad_row_to_skip() -> None:
    """Table angles are given in every row or in none: a row with one missing is refused by line, and with
    skip_bad_rows dropped and counted like any malformed row (before: refused even then)."""
    rows = [f"{t},s{t},{t},0,0,1,2,3" for t in range(1, 9)]
    rows[2] = "3,s3,3,,0,1,2,3"
    text = REQ + "\n" + "\n".join(rows) + "\n"
    with pytest.raises(RecordingError, match="empty in: line 4 .skipping bad rows drops them"):
        parse_recording(text)
    rec = parse_recording(text, skip_bad_rows=True)
    assert len(rec) == 7 and rec.meta["skipped_rows"] == "1" and rec.meta["skipped_at_rows"] == "2"
    assert rec.has_angles and [file_row(rec, i) for i in (1, 2)] == [1, 3]


def test_a_reading_beyond_any_sensor_is_a_malformed_cell() -> None:
    """1e40 in a magnetometer cell was stored as a reading (its square overflows downstream): refused by
    line and column, and skipped with the bad rows."""
    text = f"{REQ}\n0,a,0,0,0,1,2,3\n1,b,0,0,0,1e40,2,3\n2,c,0,0,0,1,2,3\n"
    with pytest.raises(RecordingError, match="line 3: column mx: 1e40 is beyond any sensor's reading"):
        parse_recording(text)
    assert parse_recording(text, skip_bad_rows=True).step.tolist() == ["a", "c"]
