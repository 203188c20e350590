"""Intel 5300 CSI Tool records: framing, bit-exact decoding and scaling, vectorized over records.

The results equal those of the tool's own `read_bf_file.m` (raw CSI, antenna permutation) and
`get_scaled_csi.m` (CSI in units of the noise). Nothing decoded here raises on bad bytes:
records with other codes, corrupt records and garbage are skipped and counted, and framing
resynchronizes on the next consistent beamforming header, the same whether a log is decoded
whole or fed in chunks (StreamDecoder).

- `records`: what the format is: codes, sizes, the header layout, the antenna permutation, where
  each value's bits lie, and the decoded records (CsiRecords, concat).
- `decoding`: records already framed to CsiRecords: bit unpacking and scaling (decode_bfee).
- `framing`: where the records of a byte stream are, through damage (decode_log, read_dat,
  split_records, StreamDecoder).
- `encoding`: the exact inverse of decoding, for the simulator and tests (encode_record).
"""

from rover.formats.intel5300.decoding import decode_bfee
from rover.formats.intel5300.encoding import RecordHeader, encode_record
from rover.formats.intel5300.framing import StreamDecoder, decode_log, read_dat, split_records
from rover.formats.intel5300.records import SUBCARRIERS, CsiFormatError, CsiRecords, LogCounts, concat

__all__ = [
    "SUBCARRIERS",
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
