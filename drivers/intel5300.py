"""The documented import path of the Intel 5300 decoder; the format lives in `rover.formats.intel5300`."""

from rover.formats.intel5300 import (
    CsiFormatError,
    CsiRecords,
    LogCounts,
    RecordHeader,
    StreamDecoder,
    concat,
    decode_bfee,
    decode_log,
    encode_record,
    read_dat,
    split_records,
)

__all__ = [
    "CsiFormatError",
    "CsiRecords",
    "LogCounts",
    "RecordHeader",
    "StreamDecoder",
    "concat",
    "decode_bfee",
    "decode_log",
    "encode_record",
    "read_dat",
    "split_records",
]
