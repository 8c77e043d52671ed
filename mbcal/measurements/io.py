"""Measurement files and plans (meas_r in the seed paper): CSV and JSON.

A measurement names its kind, what it refers to (a camera and a point, ...), its value(s), its
uncertainty (σ, per-value σ, or a full covariance), and its configuration.  Files may also give
known parameter values, globally or per configuration (a robot's joint readings in each
attitude).  A *plan* is the same file without values: it says what will be measured.

CSV (one measurement per row; columns in any order; unused cells empty; ``#`` lines are
comments)::

    id,kind,config,camera,point,u,v,sigma
    m1,image_point,pose1,left,hand.tip,312.4,201.9,0.5
    ,known,pose1,,,,,            <- rows of kind 'known' set parameters: columns param, value, unit

JSON::

    {"known": {"lever.angle": "20 deg"},
     "configurations": {"pose1": {"arm.q1": "12.5 deg", "arm.q2": 0.1}},
     "measurements": [
        {"id": "m1", "kind": "image_point", "config": "pose1", "camera": "left",
         "point": "hand.tip", "u": 312.4, "v": 201.9, "sigma": 0.5}]}

Values are SI (metres, radians, pixels) unless the row gives a ``unit`` (a ``known`` row's
``unit`` cell is read like a unit written after its value, and checked against the
parameter's dimension).  JSON records take the CSV's columns as keys (less ``param``, plus
``comment``); any other key is an error.  A per-configuration parameter given in some
configurations must be given in all of them.  Every problem is reported as
``file:line:col: message`` (docs/cli.md, "Measurement files").
"""

from __future__ import annotations

import codecs
import csv
import io
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from mbcal.errors import MbcalError, MeasurementFileError, SourceSpan, shown, suggest, undecodable_at
from mbcal.measurements.registry import get_model
from mbcal.measurements.sets import (
    DEFAULT_CONFIG,
    MAX_MEASUREMENTS,
    Measurement,
    MeasurementSet,
    SetBuilder,
    csv_columns,
    measurements_from_records,
    merge_measurements,
    parse_quantity,
    record_keys,
)
from mbcal.outputs import atomic_write

__all__ = [
    "read_measurements",
    "write_measurements",
    # defined in mbcal.measurements.sets; kept here for existing importers
    "Measurement",
    "MeasurementSet",
    "merge_measurements",
    "measurements_from_records",
    "parse_quantity",
    "DEFAULT_CONFIG",
    "MAX_MEASUREMENTS",
]

MAX_FILE_BYTES = 512 * 1024 * 1024
FORMAT = "mbcal-measurements-1"  # a JSON file's "format": the one this version writes and reads


# ---- CSV ---------------------------------------------------------------------------------------------


def _field_columns(line: str, n: int) -> list[int]:
    """1-based character columns where each of n comma-separated fields starts (best effort)."""
    cols, pos = [], 1
    if '"' in line:
        return [1] * n
    for part in line.split(","):
        cols.append(pos)
        pos += len(part) + 1
    return (cols + [pos] * n)[:n]


class _Lines:
    """The lines of a file opened in binary, decoded as UTF-8 one at a time (a byte-order mark
    skipped), remembering the last one (for the header's column positions); undecodable bytes
    are an error at their line."""

    def __init__(self, handle, path: str):
        self.handle = handle
        self.path = path
        self.last = ""
        self.number = 0
        self.pending: list[str] = []  # the rest of a line with bare CR line ends (old Mac CSV)

    def __iter__(self):
        return self

    def __next__(self) -> str:
        if self.pending:
            self.number += 1
            self.last = self.pending.pop(0)
            return self.last
        raw = next(self.handle)
        self.number += 1
        if self.number == 1 and raw.startswith(codecs.BOM_UTF8):
            raw = raw[len(codecs.BOM_UTF8) :]
        try:
            line = raw.decode("utf-8")
        except UnicodeDecodeError as err:
            # the byte within its line: a file with bare CR line ends comes as one piece
            line_start = max(raw.rfind(b"\r", 0, err.start), raw.rfind(b"\n", 0, err.start)) + 1
            raise MeasurementFileError(
                f"not UTF-8 text (byte {err.start - line_start + 1} of the line)",
                undecodable_at(self.path, err, self.number),
            ) from None
        if "\r" in line.rstrip("\r\n"):
            first, *self.pending = line.splitlines(keepends=True)
            line = first
        self.last = line
        return line


def _csv_rows(reader: Any, path: str) -> Iterator[list[str]]:
    """The reader's rows; what the csv module cannot read (a cell over its size limit) is an error
    at its line."""
    while True:
        start = reader.line_num + 1  # the record's first line (a quoted cell may span lines)
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as err:
            text = str(err)
            if "unexpected end of data" in text:
                text = "a quoted cell opened in this row is never closed"
            raise MeasurementFileError(f"unreadable CSV: {text}", SourceSpan(path, start, 1)) from None
        yield row


def _read_csv(handle, path: str, builder: SetBuilder) -> None:
    """Read CSV rows from a file opened in binary, one line at a time: memory grows with the
    measurements, not with the file (its text is never held whole)."""
    lines = _Lines(handle, path)
    reader = csv.reader(lines, strict=True)  # text after a closing quote is an error, not glued on
    header: list[str] | None = None
    allowed = csv_columns()
    for row in _csv_rows(reader, path):
        line_no = reader.line_num
        if not row or all(not c.strip() for c in row):
            continue
        if row[0].lstrip().startswith("#") and not lines.last.lstrip().startswith('"'):
            continue  # a comment line (a quoted first cell that starts with '#' is a value: an id)
        if header is None:
            header = [c.strip().lower() for c in row]
            cols = _field_columns(lines.last.rstrip("\r\n"), len(header))
            for i, name in enumerate(header):
                if name == "configuration":
                    header[i] = "config"
                elif name not in allowed:
                    raise MeasurementFileError(
                        f"unknown column '{name}'", SourceSpan(path, line_no, cols[i]), hint=suggest(name, allowed)
                    )
            if "kind" not in header:
                raise MeasurementFileError("missing column 'kind' in the header", SourceSpan(path, line_no, 1))
            dupes = {c for c in header if header.count(c) > 1 and c}
            if dupes:
                raise MeasurementFileError(f"column '{sorted(dupes)[0]}' appears twice", SourceSpan(path, line_no, 1))
            continue
        where = SourceSpan(path, line_no, 1)
        if len(row) > len(header):
            extra = [c for c in row[len(header) :] if c.strip()]
            if extra:
                raise MeasurementFileError(f"row has {len(row)} fields but the header has {len(header)}", where)
        if len(row) < len(header):
            # Padding would read what is there as other columns' values (a σ left off, or a
            # value shifted into the σ column): every cell up to the last column is written.
            raise MeasurementFileError(
                f"row has {len(row)} fields but the header has {len(header)}",
                where,
                hint="write every cell up to the header's last column; an empty cell (',,') leaves a value out",
            )
        record = {h: row[i].strip() for i, h in enumerate(header) if h}
        if record.get("kind", "").lower() == "known":
            unit = record.get("unit") or None
            unit_where = where
            if unit:  # the unit cell, for an error in it (a dimension that does not fit)
                cells = _field_columns(lines.last.rstrip("\r\n"), len(row))
                unit_where = SourceSpan(path, line_no, cells[header.index("unit")])
            try:
                builder.known_value(
                    record.get("param", ""),
                    record.get("value", ""),
                    record.get("config") or None,
                    where,
                    unit=unit,
                    unit_where=unit_where,
                )
            except MeasurementFileError as err:
                # about the parameter (its name, its configuration) or else about its value: that cell
                if err.span == where and (err.field or "value") in header:
                    cells = _field_columns(lines.last.rstrip("\r\n"), len(row))
                    column = header.index(err.field or "value")
                    if column < len(cells):
                        err.span = SourceSpan(path, line_no, cells[column])
                raise
            continue
        try:
            builder.add(record, where, len(builder.measurements) + 1)
        except MeasurementFileError as err:
            # An error about one cell points at that cell, not at the row (found only on error:
            # the columns of a row cost a scan of its line).
            if err.field in header and err.span == where:
                cells = _field_columns(lines.last.rstrip("\r\n"), len(row))
                column = header.index(err.field)
                if column < len(cells):
                    err.span = SourceSpan(path, line_no, cells[column])
            raise
    if header is None:
        raise MeasurementFileError("empty file: no header row", SourceSpan(path, 1, 1))


# ---- JSON --------------------------------------------------------------------------------------------


def _json_line_index(text: str) -> list[int]:
    """Character offsets of the elements of the top-level "measurements" array (or top-level array)."""
    decoder = json.JSONDecoder()
    start = _top_value(text, "measurements")
    if start is None:
        stripped = text.lstrip()
        if not stripped.startswith("["):
            return []
        start = text.index("[")
    elif not text.startswith("[", start):
        return []
    pos = start + 1
    offsets = []
    try:
        while True:
            while pos < len(text) and text[pos] in " \t\r\n,":
                pos += 1
            if pos >= len(text) or text[pos] == "]":
                break
            offsets.append(pos)
            _, pos = decoder.raw_decode(text, pos)
    except ValueError:
        return offsets
    return offsets


def _object_keys(text: str, start: int) -> list[tuple[str, int]]:
    """The keys of the JSON object whose ``{`` is at offset ``start``, with their offsets, in the
    order written (a key written twice is listed twice; best effort: stops at what it cannot read)."""
    decoder = json.JSONDecoder()
    pos = start + 1
    keys: list[tuple[str, int]] = []
    try:
        while True:
            while pos < len(text) and text[pos] in " \t\r\n,":
                pos += 1
            if pos >= len(text) or text[pos] != '"':
                break
            key, end = decoder.raw_decode(text, pos)
            keys.append((str(key), pos))
            pos = end
            while pos < len(text) and text[pos] in " \t\r\n:":
                pos += 1
            _, pos = decoder.raw_decode(text, pos)
    except ValueError:
        pass
    return keys


def _key_offset(text: str, start: int, key: str, value: bool = True) -> int | None:
    """The offset of ``key`` of the object at offset ``start`` (as written, else without case:
    a record's keys ignore case), or of its value with ``value``; None when it cannot be found."""
    keys = _object_keys(text, start)
    offset = next((at for k, at in keys if k == key), None)
    if offset is None:
        offset = next((at for k, at in keys if k.lower() == key.lower()), None)
    if offset is None:
        return None
    if value:
        offset = json.JSONDecoder().raw_decode(text, offset)[1]
        while offset < len(text) and text[offset] in " \t\r\n:":
            offset += 1
    return offset


def _top_value(text: str, key: str, value: bool = True) -> int | None:
    """The offset of the value of ``key`` in the file's top-level object (not a key of that name
    in some nested object: a "comment" object may hold one too), or of the key itself."""
    start = len(text) - len(text.lstrip())
    return _key_offset(text, start, key, value) if text.startswith("{", start) else None


def _key_span(text: str, path: str, start: int, key: str, value: bool = True) -> SourceSpan | None:
    """Where ``key`` of the object at offset ``start`` (see :func:`_key_offset`) is written, or
    its value with ``value``; None when it cannot be found."""
    offset = _key_offset(text, start, key, value)
    return None if offset is None else SourceSpan.at_offset(path, text, offset)


def _json_key_spans(text: str, path: str, section: str) -> dict[str, SourceSpan]:
    """Where each key of the top-level object ``section`` ("known", "configurations") is written
    (best effort: keys not found are left out)."""
    start = _top_value(text, section)
    if start is None or not text.startswith("{", start):
        return {}
    spans: dict[str, SourceSpan] = {}
    for key, offset in _object_keys(text, start):
        spans.setdefault(key, SourceSpan.at_offset(path, text, offset))
    return spans


class _DuplicateKeyError(Exception):
    """A JSON object names one key twice (raised while parsing; ``start``: the object's offset)."""

    def __init__(self, key: str) -> None:
        super().__init__(key)
        self.key = key
        self.start: int | None = None


def _unique_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    seen: set[str] = set()
    for key, _ in pairs:
        if key in seen:
            raise _DuplicateKeyError(key)
        seen.add(key)
    return dict(pairs)


def _duplicate_key_span(text: str, path: str, key: str) -> SourceSpan:
    """Where the second ``key`` of the object that names it twice is written: the file is parsed
    again by json's Python scanner, which tells the object's offset (only after a duplicate is
    found: the C parser is the fast path)."""
    decoder = json.JSONDecoder(object_pairs_hook=_unique_pairs)
    plain = decoder.parse_object  # type: ignore[attr-defined]

    def parse_object(s_and_end: tuple[str, int], *rest: Any) -> Any:
        try:
            return plain(s_and_end, *rest)
        except _DuplicateKeyError as dup:
            if dup.start is None:  # the innermost object: the one that names the key twice
                dup.start = s_and_end[1] - 1
            raise

    decoder.parse_object = parse_object  # type: ignore[attr-defined]
    decoder.scan_once = json.scanner.py_make_scanner(decoder)  # type: ignore[attr-defined]
    try:
        decoder.decode(text)
    except _DuplicateKeyError as dup:
        offsets = [offset for k, offset in _object_keys(text, dup.start or 0) if k == key]
        if len(offsets) > 1:
            return SourceSpan.at_offset(path, text, offsets[1])
        return SourceSpan.at_offset(path, text, dup.start or 0)
    return SourceSpan(path, 1, 1)


def _json_integer(digits: str) -> int | float:
    """An integer of the file; one with more digits than a float's range as a float (infinite,
    then refused where it is read, at its place), not Python's error for a long integer."""
    return int(digits) if len(digits) <= 308 else float(digits)


def _load_json(text: str, path: str) -> Any:
    """The parsed file; invalid JSON and a key written twice in one object (json keeps the last
    silently) are errors at their place."""
    try:
        return json.loads(text, object_pairs_hook=_unique_pairs, parse_int=_json_integer)
    except json.JSONDecodeError as err:
        raise MeasurementFileError(f"invalid JSON: {err.msg}", SourceSpan(path, err.lineno, err.colno)) from None
    except RecursionError:
        raise MeasurementFileError("invalid JSON: nested too deeply", SourceSpan(path, 1, 1)) from None
    except _DuplicateKeyError as dup:
        raise MeasurementFileError(
            f"key '{dup.key}' written twice in one object",
            _duplicate_key_span(text, path, dup.key),
            hint="JSON keeps only the last of the two; write the key once",
        ) from None


def _read_json(text: str, path: str, builder: SetBuilder) -> None:
    doc = _load_json(text, path)
    if isinstance(doc, list):
        doc = {"measurements": doc}
    if not isinstance(doc, dict):
        raise MeasurementFileError(
            "the file must hold an object with 'measurements' (or a list)", SourceSpan(path, 1, 1)
        )
    top = SourceSpan(path, 1, 1)

    def key_at(key: str, value: bool = True) -> SourceSpan:
        offset = _top_value(text, key, value)
        return top if offset is None else SourceSpan.at_offset(path, text, offset)

    unknown = set(doc) - {"measurements", "known", "configurations", "images", "format", "model", "comment"}
    if unknown:
        key = sorted(unknown)[0]
        raise MeasurementFileError(
            f"unknown key '{key}'",
            key_at(key, value=False),
            hint=suggest(key, ["measurements", "known", "configurations"]),
        )
    if "format" in doc and doc["format"] != FORMAT:  # another program's file, or one of a later mbcal
        raise MeasurementFileError(
            f"'format' is {shown(doc['format'])}: this mbcal reads measurement files of format '{FORMAT}'",
            key_at("format"),
        )
    known = doc.get("known", {})
    if not isinstance(known, dict):
        raise MeasurementFileError("'known' must map parameter names to values", top)
    known_at = _json_key_spans(text, path, "known") if known else {}
    for name, value in known.items():
        builder.known_value(name, value, None, known_at.get(name, top))
    configs = doc.get("configurations", {})
    if not isinstance(configs, dict):
        raise MeasurementFileError("'configurations' must map configuration names to {parameter: value}", top)
    config_at = _json_key_spans(text, path, "configurations") if configs else {}
    for config, values in configs.items():
        at = config_at.get(config, top)
        if not isinstance(values, dict):
            raise MeasurementFileError(f"configuration '{config}' must map parameter names to values", at)
        builder.configuration(str(config), at)
        for name, value in values.items():
            builder.known_value(name, value, str(config), at)
    images = doc.get("images", {})
    if not isinstance(images, dict) or not all(isinstance(v, str) for v in images.values()):
        raise MeasurementFileError("'images' must map configuration names to image files", top)
    base = Path(path).resolve().parent
    builder.images = {str(k): str(base / v) for k, v in images.items()}
    items = doc.get("measurements")
    if not isinstance(items, list):
        raise MeasurementFileError("'measurements' must be a list", top)
    offsets = _json_line_index(text)
    allowed = record_keys()
    # Lines counted up to offset `counted`, whose line starts at `start` (the records come in order:
    # counting each from the file's start was quadratic, 46 ms for 702 corners).
    counted, line, start = 0, 1, 0
    for i, item in enumerate(items):
        if i < len(offsets):
            off = offsets[i]
            if off < counted:
                counted, line, start = 0, 1, 0
            line += text.count("\n", counted, off)
            start = max(start, text.rfind("\n", counted, off) + 1)
            counted = off
            where = SourceSpan(path, line, off - start + 1)
        else:
            where = SourceSpan(path, 1, 1)
        if not isinstance(item, dict):
            raise MeasurementFileError(f"measurements[{i}] must be an object", where)
        record = {k.lower(): v for k, v in item.items()}
        if len(record) < len(item):  # keys are read without case: "Sigma" and "sigma" are one key
            twice = next(k for k in record if sum(1 for j in item if j.lower() == k) > 1)
            raise MeasurementFileError(f"key '{twice}' written twice in measurements[{i}] (keys ignore case)", where)
        for key in record:
            if key not in allowed:  # a typo ("sigam") would silently be the default
                raise MeasurementFileError(
                    f"unknown key '{key}'",
                    (_key_span(text, path, offsets[i], key, value=False) if i < len(offsets) else None) or where,
                    hint=suggest(key, allowed),
                )
        if "configuration" in record:
            other = record.pop("configuration")
            if record.get("config", other) != other:
                raise MeasurementFileError(
                    f"'config' ({shown(record['config'])}) and 'configuration' ({shown(other)}) name different "
                    "configurations",
                    where,
                )
            record["config"] = other
        try:
            builder.add(record, where, i + 1)
        except MeasurementFileError as err:
            # An error about one value points at it, not at the record's '{' (found only on error).
            if err.field and err.span == where and i < len(offsets):
                err.span = _key_span(text, path, offsets[i], err.field.lower()) or where
            raise


def read_measurements(path: str | os.PathLike[str], model=None) -> MeasurementSet:
    """Read a measurement file or plan (``.csv`` or ``.json``).

    Parameters
    ----------
    path : path
    model : Model, optional
        Names are resolved against it (unique dotted suffixes allowed) and checked; without a
        model they are kept as written.

    Raises
    ------
    MeasurementFileError
        With ``file:line:col`` for unknown names, kinds or columns, non-finite numbers, missing
        values or columns, wrong arity, duplicate ids, bad σ or covariance.
    """
    p = Path(path)
    display = str(path)
    try:
        size = p.stat().st_size
    except FileNotFoundError:
        raise MeasurementFileError(f"file not found: {display}") from None
    except OSError as err:
        raise MeasurementFileError(f"cannot read {display}: {err.strerror}") from None
    if p.is_dir():
        raise MeasurementFileError(f"{display} is a folder, not a measurement file")
    if size > MAX_FILE_BYTES:
        raise MeasurementFileError(f"{display} is larger than {MAX_FILE_BYTES // 2**20} MiB")
    builder = SetBuilder(model, display)
    suffix = p.suffix.lower()
    builder.row_word = "row" if suffix in (".csv", ".txt") else "measurement"
    if suffix in (".csv", ".txt"):
        # Streamed row by row (docs/reliability.md: 10⁶ rows).
        with open(p, "rb") as handle:
            _read_csv(handle, display, builder)
        return builder.result()
    if suffix != ".json":
        raise MeasurementFileError(f"unknown measurement file type '{p.suffix}' (use .csv or .json)")
    try:
        text = p.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise MeasurementFileError(f"not UTF-8 text (byte {err.start + 1})", undecodable_at(display, err)) from None
    _read_json(text, display, builder)
    return builder.result()


# ---- writing -----------------------------------------------------------------------------------------


def _record(m: Measurement) -> dict[str, Any]:
    mm = get_model(m.kind)
    rec: dict[str, Any] = {"id": m.id, "kind": m.kind, "config": m.config}
    rec.update(m.refs)
    rec.update({k: (int(v) if k in mm.integer_data else v) for k, v in m.data.items()})
    if m.value is not None and mm.implicit_value is None:
        rec.update({n: float(v) for n, v in zip(mm.values, m.value)})
    sig = m.sigma
    off_diagonal = np.any(np.abs(m.cov - np.diag(np.diag(m.cov))) > 0)
    if off_diagonal:
        rec["cov"] = m.cov.tolist()
    elif np.allclose(sig, sig[0]):
        rec["sigma"] = float(sig[0])
    else:
        rec.update({f"sigma_{n}": float(s) for n, s in zip(mm.values, sig)})
    return rec


def write_measurements(ms: MeasurementSet, path: str | os.PathLike[str]) -> None:
    """Write a measurement set as ``.csv`` or ``.json`` (atomically; values in SI units)."""
    p = Path(path)
    records = [_record(m) for m in ms.measurements]
    if p.suffix.lower() == ".json":
        doc: dict[str, Any] = {"format": FORMAT}
        if ms.known:
            doc["known"] = ms.known
        if ms.configurations:
            doc["configurations"] = ms.configurations
        if ms.images:
            folder = p.resolve().parent
            doc["images"] = {k: os.path.relpath(v, folder) for k, v in ms.images.items()}
        doc["measurements"] = records
        atomic_write(p, json.dumps(doc, indent=1) + "\n")
        return
    if p.suffix.lower() != ".csv":
        raise MeasurementFileError(f"cannot write '{p.suffix}' measurement files (use .csv or .json)")
    columns = ["id", "kind", "config"]
    for r in records:
        for k in r:
            if k not in columns and k != "cov":
                columns.append(k)
    if any("cov" in r for r in records):
        columns.append("cov")
    if ms.known or ms.configurations:
        for extra in ("param", "value"):
            if extra not in columns:
                columns.append(extra)
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(columns)
    for name, value in ms.known.items():
        writer.writerow(
            [
                "" if c not in ("kind", "param", "value") else {"kind": "known", "param": name, "value": repr(value)}[c]
                for c in columns
            ]
        )
    for config, values in ms.configurations.items():
        for name, value in values.items():
            row = {"kind": "known", "config": config, "param": name, "value": repr(value)}
            writer.writerow([row.get(c, "") for c in columns])
    for r in records:
        cells = []
        for c in columns:
            v = r.get(c, "")
            if c == "cov" and v != "":
                v = ";".join(repr(float(x)) for x in np.ravel(v))
            elif isinstance(v, float):
                v = repr(v)
            cells.append(v)
        first = str(cells[0])
        if first != first.strip():  # the reader strips cells: the id would come back another
            raise MbcalError(
                f"measurement id {first!r} begins or ends with a space, which a CSV file does not keep",
                hint="write a .json file, or rename the measurement",
            )
        if first.startswith("#"):  # quoted, or the reader would take the row for a comment
            out.write('"' + first.replace('"', '""') + '"')
            rest = io.StringIO()
            csv.writer(rest, lineterminator="\n").writerow(cells[1:])
            out.write("," + rest.getvalue() if len(cells) > 1 else "\n")
            continue
        writer.writerow(cells)
    atomic_write(p, out.getvalue())
