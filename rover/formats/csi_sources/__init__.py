"""CSI captures of other tools than the Intel 5300's CSI Tool, read into one frame (`CsiFrames`):
the Atheros CSI Tool, Nexmon CSI and PicoScenes, through csiread, the format found from the file's
contents (`read_capture`)."""

from rover.formats.csi_sources.detect import FORMATS, detect_format, read_capture
from rover.formats.csi_sources.frames import CsiFrames

__all__ = ["FORMATS", "CsiFrames", "detect_format", "read_capture"]
