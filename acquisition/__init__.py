"""Acquisition: camera, hammer and DAQ drivers, triggering, hit QC and the guided capture session."""
