"""Reading the text files users deliver (TUM, CSV, JSON): UTF-8 or a clear error, rows with their
line numbers, numbers checked, and excerpts safe to quote in a one-line message."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterator
from pathlib import Path

from rover.errors import BadInput


def read_text(path: str | Path) -> str:
    """A UTF-8 text file's content (a byte-order mark dropped); BadInput naming the file when it
    cannot be read or holds bytes that are not text."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise BadInput(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise BadInput(
            f"{path}: not a text file (byte 0x{data[exc.start]:02x} at offset {exc.start} is not UTF-8)"
        ) from None
    if "\x00" in text:
        raise BadInput(f"{path}: not a text file (NUL byte at offset {data.index(0)})")
    return text


def excerpt(line: str, limit: int = 60) -> str:
    """A line quoted for a one-line message: control characters escaped, long lines cut."""
    text = line.strip()
    return repr(text if len(text) <= limit else text[:limit] + "...")


def csv_rows(
    text: str, source: str, required: tuple[str, ...], expected: str = ""
) -> Iterator[tuple[int, dict[str, str]]]:
    """The rows of a CSV text with a header line, by column name, with their line numbers; BadInput
    naming `source` for a missing column (`expected` says which are, by default `required`), a row
    without a value for one, or text that is not CSV."""
    reader = csv.reader(io.StringIO(text.removeprefix("\ufeff"), newline=""))
    try:
        header = [name.strip() for name in next(reader, [])]
        missing = [c for c in required if c not in header]
        if missing:
            expected = expected or ",".join(required)
            raise BadInput(f"{source}:1: missing column(s) {', '.join(missing)} (expected {expected})")
        for fields in reader:
            if not any(f.strip() for f in fields):
                continue
            if len(fields) < len(header) and (absent := [c for c in required if c not in header[: len(fields)]]):
                raise BadInput(
                    f"{source}:{reader.line_num}: {len(fields)} field(s), no value for column(s) {', '.join(absent)}"
                )
            yield reader.line_num, dict(zip(header, fields, strict=False))
    except csv.Error as exc:
        raise BadInput(f"{source}:{reader.line_num}: not CSV: {exc}") from None


def csv_float(row: dict[str, str], column: str, where: str) -> float:
    """A finite number from a CSV row; BadInput at `where` naming the column."""
    text = row.get(column, "").strip()
    try:
        value = float(text)
    except ValueError:
        raise BadInput(f"{where}: column {column} is {excerpt(text, 20) if text else 'empty'}, not a number") from None
    if not math.isfinite(value):
        raise BadInput(f"{where}: column {column} has a non-finite value {excerpt(text, 20)}")
    return value


def csv_int(row: dict[str, str], column: str, where: str, limit: int) -> int:
    """An integer in [0, limit) from a CSV row; BadInput at `where` naming the column."""
    text = row.get(column, "").strip()
    try:
        value = int(text)
    except ValueError:
        raise BadInput(
            f"{where}: column {column} is {excerpt(text, 20) if text else 'empty'}, not an integer"
        ) from None
    if not 0 <= value < limit:
        raise BadInput(
            f"{where}: column {column} is {text if len(text) <= 20 else excerpt(text, 20)}, outside 0..{limit - 1}"
        )
    return value


def tag_rows(
    text: str, source: str, required: tuple[str, ...], expected: str = ""
) -> Iterator[tuple[str, int, dict[str, str]]]:
    """The rows of a CSV of tags, one per `id`: (where, id, row); BadInput at the line of a repeated id."""
    first_line: dict[int, int] = {}
    for number, row in csv_rows(text, source, required, expected):
        where = f"{source}:{number}"
        tag_id = csv_int(row, "id", where, 2**32)
        if tag_id in first_line:
            raise BadInput(f"{where}: tag id {tag_id} repeated (first on line {first_line[tag_id]})")
        first_line[tag_id] = number
        yield where, tag_id, row
