"""Recording file format (CSV text): parse and format, see shared/design/RECORDING.md.

Works on text only; reading and writing files is the caller's business.
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

VERSION_KEY = "compasscal-recording"
FORMAT_VERSION = "1"
SKIPPED_KEY = "skipped_rows"
#: The largest magnitude a magnetometer or accelerometer cell may hold (counts): far beyond any converter
#: (int16, int32 at 2e9), so only a corrupt cell is refused (1e40 was stored, and its squares overflow).
MAX_READING = 1e10
#: The 0-based data rows of the file that are not in the recording (a parse note, as SKIPPED_KEY): the
#: malformed rows skip_bad_rows dropped, and a mapped file's rows without a reference attitude.
SKIPPED_AT_KEY = "skipped_at_rows"

ANGLE_COLUMNS = ("psi_t", "theta_t", "phi_t")
MAG_COLUMNS = ("mx", "my", "mz")
ACC_COLUMNS = ("ax", "ay", "az")
REQUIRED_COLUMNS = ("t", "step", *ANGLE_COLUMNS, *MAG_COLUMNS)
KNOWN_COLUMNS = (*REQUIRED_COLUMNS, *ACC_COLUMNS, "temp_c")
# Printed decimals per numeric column; parse(format(rec)) is exact to this precision.
DECIMALS = {"t": 3, **{c: 4 for c in ANGLE_COLUMNS}, **{c: 2 for c in (*MAG_COLUMNS, *ACC_COLUMNS)}, "temp_c": 2}
MAX_LISTED_PROBLEMS = 20
_LINE_BREAK = re.compile(r"\r\n|\r|\n")


class RecordingError(ValueError):
    """Bad recording input. Message names the line number(s), the column/field and the problem."""


@dataclass(eq=False)  # eq=False: comparing numpy arrays field-wise has no single truth value
class Recording:
    """One unit's samples. Angles in degrees, mag/acc in raw LSB, t in seconds (non-decreasing)."""

    t: np.ndarray
    step: np.ndarray
    psi_t: np.ndarray
    theta_t: np.ndarray
    phi_t: np.ndarray
    mag: np.ndarray
    acc: np.ndarray | None = None
    temp_c: np.ndarray | None = None
    meta: dict[str, str] = field(default_factory=dict)
    extra: dict[str, list[str]] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def has_angles(self) -> bool:
        """False for a recording without table angles (a hand-held one: the angle cells are empty)."""
        return not bool(np.isnan(self.psi_t).all() and np.isnan(self.theta_t).all() and np.isnan(self.phi_t).all())

    @property
    def serial(self) -> str | None:
        """The unit's serial number from the metadata, if recorded."""
        return self.meta.get("serial")

    def fingerprint(self) -> int:
        """A 52-bit number (exact in JSON, whose numbers are doubles) drawn from the recording's readings, angles and times, each rounded to the
        decimals its file keeps (`DECIMALS`): the same recording gives the same number whether it was read
        from a file, an export of it or the database. The analyser seeds its null simulations with it."""
        h = hashlib.sha256()
        columns = [("t", self.t), *((c, getattr(self, c)) for c in ANGLE_COLUMNS), ("mx", self.mag),
                   ("ax", self.acc), ("temp_c", self.temp_c)]
        for name, values in columns:
            if values is None:
                h.update(b"-")
                continue
            v = np.round(np.asarray(values, dtype=float), DECIMALS[name]) + 0.0  # + 0.0: -0.0 hashes as 0.0
            h.update(np.where(np.isnan(v), np.inf, v).astype("<f8").tobytes())
        return int.from_bytes(h.digest()[:8], "little") >> 12

    def select(self, mask_or_index: Any) -> Recording:
        """Return a new Recording with the rows picked by a boolean mask, index array, slice or int."""
        idx = [mask_or_index] if isinstance(mask_or_index, (int, np.integer)) else mask_or_index
        if not isinstance(idx, slice):
            idx = np.asarray(idx)
        pick = lambda a: None if a is None else np.asarray(a)[idx].copy()  # noqa: E731
        return Recording(
            t=pick(self.t), step=pick(self.step), psi_t=pick(self.psi_t), theta_t=pick(self.theta_t),
            phi_t=pick(self.phi_t), mag=pick(self.mag), acc=pick(self.acc), temp_c=pick(self.temp_c),
            meta=dict(self.meta),
            extra={k: np.asarray(v, dtype=object)[idx].tolist() for k, v in self.extra.items()},
        )

    @classmethod
    def from_arrays(cls, t: Any, step: Any, psi_t: Any, theta_t: Any, phi_t: Any, mag: Any,
                    acc: Any = None, temp_c: Any = None, meta: dict[str, str] | None = None,
                    extra: dict[str, list[str]] | None = None) -> Recording:
        """Build a Recording from array-likes, converting dtypes and checking shapes and values.

        An acc or temp_c that is NaN everywhere becomes None, as it would after a format/parse trip.
        """
        t = np.asarray(t, dtype=float)
        if t.ndim != 1:
            raise RecordingError(f"t must be 1-D, got shape {t.shape}")
        n = len(t)
        if isinstance(step, str) or np.ndim(step) != 1 or len(step) != n:
            raise RecordingError(f"step must be a sequence of {n} labels")
        rec = cls(
            t=t,
            step=np.array([str(s) for s in step], dtype=object),
            psi_t=_float_array("psi_t", psi_t, (n,)),
            theta_t=_float_array("theta_t", theta_t, (n,)),
            phi_t=_float_array("phi_t", phi_t, (n,)),
            mag=_float_array("mag", mag, (n, 3)),
            acc=None if acc is None else _float_array("acc", acc, (n, 3)),
            temp_c=None if temp_c is None else _float_array("temp_c", temp_c, (n,)),
            meta={str(k): str(v) for k, v in (meta or {}).items()},
            extra={str(k): [str(x) for x in v] for k, v in (extra or {}).items()},
        )
        if rec.acc is not None and np.isnan(rec.acc).all():
            rec.acc = None
        if rec.temp_c is not None and np.isnan(rec.temp_c).all():
            rec.temp_c = None
        _validate(rec)
        return rec


def _float_array(name: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != shape:
        raise RecordingError(f"{name} has shape {arr.shape}, expected {shape}")
    return arr


def _validate(rec: Recording) -> None:
    """Refuse a Recording whose text form parse_recording would reject (or misread)."""
    n = len(rec)
    # table angles may be empty in every row (a recording without them), never in some rows only
    no_angles = all(np.isnan(np.asarray(getattr(rec, a), dtype=float)).all() for a in ANGLE_COLUMNS)
    for name in ("t", *([] if no_angles else ANGLE_COLUMNS), "mag"):
        bad = np.flatnonzero(~np.isfinite(np.asarray(getattr(rec, name), dtype=float)).reshape(n, -1).all(axis=1))
        if bad.size:
            raise RecordingError(f"{name} has non-finite values at row(s) {bad[:10].tolist()}")
    for name in ("acc", "temp_c"):
        arr = getattr(rec, name)
        if arr is not None and np.isinf(arr).any():  # NaN is allowed: it means "empty cell"
            raise RecordingError(f"{name} has infinite values")
    back = np.flatnonzero(np.diff(rec.t) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise RecordingError(f"t decreases at row {i} ({rec.t[i]} < {rec.t[i - 1]})")
    for i, label in enumerate(rec.step):
        if not str(label).strip() or _LINE_BREAK.search(str(label)):
            raise RecordingError(f"step label at row {i} is empty or contains a line break: {label!r}")
    for name, values in rec.extra.items():
        if name in KNOWN_COLUMNS or not name.strip() or len(values) != n:
            raise RecordingError(f"extra column {name!r}: clashes with a known column, is blank, or has "
                                 f"{len(values)} values for {n} rows")
        if any(_LINE_BREAK.search(v) for v in values) or _LINE_BREAK.search(name):
            raise RecordingError(f"extra column {name!r} contains a line break")
    for key, value in rec.meta.items():
        if not key.strip() or ":" in key or _LINE_BREAK.search(key + value):
            raise RecordingError(f"metadata key {key!r} is blank, contains ':' or a line break (or its value does)")


def _show(raw: str, limit: int = 80) -> str:
    return raw if len(raw) <= limit else raw[: limit - 3] + "..."


def file_row(rec: Recording, index: int) -> int:
    """The 0-based data row of the file that sample ``index`` was read from (the rows after the header,
    blank and comment lines not counted): the index itself unless rows before it were left out (meta
    ``skipped_at_rows``: malformed rows skipped, a mapped file's rows without a reference), which a
    message about the sample must count to point at the right row of the file."""
    for skipped in sorted(int(x) for x in rec.meta.get(SKIPPED_AT_KEY, "").split(",") if x.strip()):
        if skipped <= index:
            index += 1
    return index


def parse_recording(text: str, *, skip_bad_rows: bool = False, max_step_chars: int | None = None) -> Recording:
    """Parse recording CSV text (RECORDING.md) into a Recording.

    Every malformed row is reported ("line L: column C: problem ('raw')"); any such row rejects the whole
    text unless skip_bad_rows, which drops them and records their count in meta["skipped_rows"].
    ``max_step_chars``: a step label longer than this is a malformed row too (a store whose column
    holds no more, e.g. the service's 32 characters).
    """
    lines = _LINE_BREAK.split(text.removeprefix("\ufeff"))
    meta: dict[str, str] = {}
    header_at = None
    for i, line in enumerate(lines):
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            key, colon, value = stripped[1:].partition(":")
            if colon and key.strip():  # "#" lines without "key:" are plain comments
                meta[key.strip()] = value.strip()
            continue
        header_at = i
        break
    if header_at is None:
        raise RecordingError("recording has no column line")
    version = meta.get(VERSION_KEY)
    if version is not None and version.removesuffix(".0") != str(FORMAT_VERSION):
        # a later format may give a column another meaning: read as this one, its numbers would be wrong
        raise RecordingError(f"metadata '# {VERSION_KEY}: {version}': this compasscal reads format {FORMAT_VERSION} "
                             "(RECORDING.md)")

    names = _parse_column_line(lines[header_at], header_at + 1)
    col = {name: j for j, name in enumerate(names)}
    has_acc, has_temp = "ax" in col, "temp_c" in col
    numeric = [c for c in KNOWN_COLUMNS if c in col and c != "step"]
    extra_names = [c for c in names if c not in KNOWN_COLUMNS]

    rows: list[dict[str, Any]] = []
    problems: list[str] = []
    bad_rows = 0
    skipped_at: list[int] = []  # data rows (0-based, good and bad counted) that were malformed
    last_t, last_t_line = -math.inf, 0
    behind: dict[str, Any] | None = None  # the second row, blamed for going back from the first (see below)
    for lineno, line in enumerate(lines[header_at + 1:], start=header_at + 2):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):  # comments after the column line are ignored too
            continue
        row, row_problems = _parse_row(line, lineno, names, col, numeric, max_step_chars)
        if (not row_problems and row["t"] < last_t and len(rows) >= 2 and row["t"] >= rows[-2]["t"]
                and row["t"] - rows[-2]["t"] < last_t - row["t"]):
            # the row before jumped ahead of both neighbours, this one going on from the row before it: that
            # one time stamp is the bad one (blaming this row instead made every row after the jump
            # "malformed"); a small step back stays this row's
            ahead = rows.pop()
            problems.append(f"line {ahead['line']}: column t: {ahead['raw_t']} is ahead of the rows before and after "
                            f"it (t={rows[-1]['t']:g} on line {rows[-1]['line']}, t={row['raw_t']} on line {lineno})")
            skipped_at.append(ahead["data_row"])
            bad_rows += 1
            last_t, last_t_line = rows[-1]["t"], rows[-1]["line"]
        if (not row_problems and row["t"] < last_t and len(rows) == 1 and behind is not None
                and behind["t"] <= row["t"]):
            # the first row is the one ahead: the row blamed for going back from it and this one go on
            # together (a bad first time stamp made every other row "malformed")
            first = rows.pop()
            problems[behind["problem"]] = (f"line {first['line']}: column t: {first['raw_t']} is ahead of the rows "
                                           f"after it (t={behind['raw_t']} on line {behind['line']}, "
                                           f"t={row['raw_t']} on line {lineno})")
            skipped_at[skipped_at.index(behind["data_row"])] = first["data_row"]
            rows.append(behind)
            last_t, last_t_line = behind["t"], behind["line"]
        behind = None
        if not row_problems and row["t"] < last_t:
            row_problems.append(f"line {lineno}: column t: time goes backwards "
                                f"(previous t={last_t:g} on line {last_t_line}) ('{row['raw_t']}')")
            if len(rows) == 1 and len(row_problems) == 1:  # perhaps the first row is the bad one: the next row tells
                behind = {**row, "line": lineno, "data_row": len(rows) + bad_rows, "problem": len(problems)}
        if row_problems:
            skipped_at.append(len(rows) + bad_rows)
            bad_rows += 1
            problems.extend(row_problems)
            continue
        last_t, last_t_line = row["t"], lineno
        row["line"], row["data_row"] = lineno, len(rows) + bad_rows
        rows.append(row)

    if problems and not skip_bad_rows:
        listed = problems[:MAX_LISTED_PROBLEMS]
        more = len(problems) - len(listed)
        raise RecordingError(f"{bad_rows} malformed row(s):\n" + "\n".join(listed)
                             + (f"\n... and {more} more" if more else ""))
    if skip_bad_rows and rows:
        # a row whose table angles are partly or wholly missing where the others have them (or the other
        # way round) is malformed too: the recording's rows share one kind
        given = np.array([[not math.isnan(r[c]) for c in ANGLE_COLUMNS] for r in rows])
        usual = given.all(axis=1).sum() * 2 >= len(rows)
        odd = ~given.all(axis=1) if usual else given.any(axis=1)
        for i in np.flatnonzero(odd):
            skipped_at.append(rows[i]["data_row"])
        bad_rows += int(odd.sum())
        rows = [r for r, o in zip(rows, odd) if not o]
    if skip_bad_rows:
        meta[SKIPPED_KEY] = str(bad_rows)
        if skipped_at:
            meta[SKIPPED_AT_KEY] = ",".join(map(str, skipped_at))
    if not rows:
        skipped = f" ({bad_rows} malformed row(s) skipped)" if bad_rows else ""
        raise RecordingError(f"recording has no data rows{skipped}")

    column = lambda c: np.array([r[c] for r in rows], dtype=float)  # noqa: E731
    empty = np.isnan(np.column_stack([column(c) for c in ANGLE_COLUMNS]))
    if empty.any() and not empty.all():
        where = [f"line {rows[i]['line']}" for i in np.flatnonzero(empty.any(axis=1))[:10]]
        raise RecordingError("table angles psi_t, theta_t, phi_t must be given in every row or left empty in every "
                             f"row (a recording without table angles); empty in: {', '.join(where)} (skipping bad rows drops them)")
    problem = time_unit_problem(column("t"), meta)
    if problem:
        raise RecordingError(problem)
    acc = np.column_stack([column(c) for c in ACC_COLUMNS]) if has_acc else None
    temp = column("temp_c") if has_temp else None
    return Recording(
        t=column("t"),
        step=np.array([r["step"] for r in rows], dtype=object),
        psi_t=column("psi_t"), theta_t=column("theta_t"), phi_t=column("phi_t"),
        mag=np.column_stack([column(c) for c in MAG_COLUMNS]),
        acc=None if acc is None or np.isnan(acc).all() else acc,
        temp_c=None if temp is None or np.isnan(temp).all() else temp,
        meta=meta,
        extra={c: [r["extra"][j] for r in rows] for j, c in enumerate(extra_names)},
    )


#: Units a time column is mistakenly written in, by seconds per unit's count ("t looks like ...").
TIME_MISTAKES = (("milliseconds", 1e-3), ("microseconds", 1e-6), ("nanoseconds", 1e-9))


def time_unit_problem(t: np.ndarray, meta: dict[str, str]) -> str | None:
    """Why ``t`` is not in seconds, when the file's own '# sample_rate_hz' says so: its samples' usual
    spacing (the median of the steps forward) is a thousand or a million times the rate's period. A
    two-minute log in milliseconds read as seconds was 29 hours long, and every analysis of it against
    time meaningless, without a word. None when there is no rate to compare with or it agrees."""
    try:
        rate = float(meta.get("sample_rate_hz", "nan"))
    except ValueError:
        return None
    steps = np.diff(t)
    steps = steps[steps > 0]
    if not (math.isfinite(rate) and rate > 0) or steps.size < 2:
        return None
    spacing = float(np.median(steps))
    for unit, seconds in TIME_MISTAKES:
        if 1 / 3 <= spacing * seconds * rate <= 3:
            return (f"column t: consecutive samples are {spacing:g} s apart (the median step) where the file's "
                    f"'# sample_rate_hz: {rate:g}' says {1 / rate:g} s: t looks like {unit}; RECORDING.md's t is in "
                    "seconds (divide it, or correct the rate line)")
    return None


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _parse_column_line(line: str, lineno: int) -> list[str]:
    try:
        names = [c.strip() for c in next(csv.reader([line], strict=True))]
    except csv.Error as exc:
        raise RecordingError(f"line {lineno}: column line: bad CSV quoting ({exc})") from None
    if sum(_is_number(c) for c in names) > len(names) // 2:  # (such a file read "duplicate column(s): 0.0000")
        raise RecordingError(f"line {lineno}: the first line that is not a comment must name the columns "
                             f"({', '.join(REQUIRED_COLUMNS)}, ...; RECORDING.md), and this one holds numbers: "
                             "the file has no column line")
    if "" in names:
        raise RecordingError(f"line {lineno}: column line: column {names.index('') + 1} has an empty name")
    dups = sorted({c for c in names if names.count(c) > 1})
    if dups:
        raise RecordingError(f"line {lineno}: duplicate column(s): {', '.join(dups)}")
    missing = [c for c in REQUIRED_COLUMNS if c not in names]
    if missing:
        raise RecordingError(f"line {lineno}: missing required column(s): {', '.join(missing)}")
    present_acc = [c for c in ACC_COLUMNS if c in names]
    if present_acc and len(present_acc) != len(ACC_COLUMNS):
        absent = [c for c in ACC_COLUMNS if c not in names]
        raise RecordingError(f"line {lineno}: accelerometer columns need all of ax, ay, az; "
                             f"missing: {', '.join(absent)}")
    return names


def _parse_row(line: str, lineno: int, names: list[str], col: dict[str, int],
               numeric: list[str], max_step_chars: int | None = None) -> tuple[dict[str, Any], list[str]]:
    """Return the row's values by column name and the list of its problems (empty when the row is good)."""
    where = f"line {lineno}"
    try:
        cells = next(csv.reader([line], strict=True))
    except csv.Error as exc:
        return {}, [f"{where}: bad CSV quoting ({exc}) ('{_show(line)}')"]
    if len(cells) != len(names):
        return {}, [f"{where}: expected {len(names)} fields, got {len(cells)} ('{_show(line)}')"]
    problems: list[str] = []
    row: dict[str, Any] = {"raw_t": _show(cells[col["t"]].strip())}  # for the time-goes-backwards message
    for c in numeric:
        raw = cells[col[c]].strip()
        if not raw:
            if c in REQUIRED_COLUMNS and c not in ANGLE_COLUMNS:  # angles: empty in every row or none
                problems.append(f"{where}: column {c}: empty required cell ('')")
            row[c] = math.nan  # empty optional cell
            continue
        try:
            if "_" in raw:  # float() accepts "1_000"; a CSV number should not
                raise ValueError
            value = float(raw)
        except ValueError:
            problems.append(f"{where}: column {c}: not a number ('{_show(raw)}')")
            continue
        if not math.isfinite(value):
            problems.append(f"{where}: column {c}: non-finite value ('{_show(raw)}')")
            continue
        if c in MAG_COLUMNS + ACC_COLUMNS and abs(value) > MAX_READING:
            problems.append(f"{where}: column {c}: {_show(raw)} is beyond any sensor's reading (|value| <= {MAX_READING:g})")
            continue
        row[c] = value
    row["step"] = cells[col["step"]].strip()
    if not row["step"]:
        problems.append(f"{where}: column step: empty required cell ('')")
    elif max_step_chars is not None and len(row["step"]) > max_step_chars:
        problems.append(f"{where}: column step: label of {len(row['step'])} characters, at most {max_step_chars} "
                        f"('{_show(row['step'])}')")
    row["extra"] = [cells[j] for j, c in enumerate(names) if c not in KNOWN_COLUMNS]  # verbatim
    return row, problems


def _full(v: float, decimals: int) -> str:
    """``v`` with at least ``decimals`` decimals and as many more as it needs to read back exactly."""
    short = repr(v)
    if "e" in short or "inf" in short:
        return short if "inf" in short else np.format_float_positional(v, unique=True, trim="-")
    fixed = f"{v:.{decimals}f}"
    return fixed if float(fixed) == v else short


def format_recording(rec: Recording, header: bool = True) -> str:
    """Format a Recording as recording CSV text (RECORDING.md); parse_recording reads it back.
    ``header=False``: the data rows only, to append to a file of the same columns.

    Raises RecordingError for a Recording whose text could not be read back (non-finite required values,
    t decreasing, empty or multi-line step labels, bad metadata keys).
    """
    _validate(rec)
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    extra_names = list(rec.extra)
    if header:
        out.write(f"# {VERSION_KEY}: {FORMAT_VERSION}\n")
        for key, value in rec.meta.items():
            if key not in (VERSION_KEY, SKIPPED_KEY, SKIPPED_AT_KEY):  # the version is ours; the skips were parse notes
                out.write(f"# {key}: {value}\n")
        writer.writerow([*KNOWN_COLUMNS, *extra_names])

    def fmt(values: np.ndarray | None, decimals: int) -> list[str]:
        # every digit the value has (the shortest text that reads back to the same float), so that an
        # export is what was recorded; ``decimals`` is how many a reading at least carries
        if values is None:
            return [""] * len(rec)
        return ["" if math.isnan(v) else _full(v, decimals) for v in np.asarray(values, dtype=float).tolist()]

    acc_cols = [None if rec.acc is None else np.asarray(rec.acc, dtype=float)[:, k] for k in range(3)]
    mag = np.asarray(rec.mag, dtype=float)
    columns = [
        fmt(rec.t, DECIMALS["t"]),
        [str(s) for s in rec.step],
        *(fmt(getattr(rec, c), DECIMALS[c]) for c in ANGLE_COLUMNS),
        *(fmt(mag[:, k], DECIMALS[c]) for k, c in enumerate(MAG_COLUMNS)),
        *(fmt(acc_cols[k], DECIMALS[c]) for k, c in enumerate(ACC_COLUMNS)),
        fmt(rec.temp_c, DECIMALS["temp_c"]),
        *(rec.extra[c] for c in extra_names),
    ]
    writer.writerows(zip(*columns))
    return out.getvalue()


def concat(recs: list[Recording]) -> Recording:
    """One recording of several in order (metadata of the first; accelerometer or temperature columns
    missing in any part become NaN there)."""
    if not recs:
        raise RecordingError("nothing to concatenate")
    n = [len(r) for r in recs]

    def column(name: str, width: int | None) -> np.ndarray | None:
        parts = [getattr(r, name) for r in recs]
        if all(p is None for p in parts):
            return None
        shape = lambda k: (k,) if width is None else (k, width)  # noqa: E731
        return np.concatenate([np.full(shape(k), np.nan) if p is None else p for p, k in zip(parts, n)])

    keys = sorted({k for r in recs for k in r.extra})
    return Recording(
        t=np.concatenate([r.t for r in recs]), step=np.concatenate([r.step for r in recs]),
        psi_t=np.concatenate([r.psi_t for r in recs]), theta_t=np.concatenate([r.theta_t for r in recs]),
        phi_t=np.concatenate([r.phi_t for r in recs]), mag=np.concatenate([r.mag for r in recs]),
        acc=column("acc", 3), temp_c=column("temp_c", None), meta=dict(recs[0].meta),
        extra={k: [x for r, m in zip(recs, n) for x in r.extra.get(k, [""] * m)] for k in keys},
    )
