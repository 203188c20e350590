"""File and record formats: Intel 5300 CSI records, the rig file, TUM and tags CSV, MCAP datasets, the run directory."""
