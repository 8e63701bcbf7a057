"""Calibration of the projector-camera rig (camera, projector, stereo, phase-to-height)."""
