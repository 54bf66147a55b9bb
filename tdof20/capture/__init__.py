"""Capture: plan and run a session on the rig (or the simulator), resume it, verify it."""

from tdof20.capture.config import CaptureConfig, config_from_dict, load_config, sim_config
from tdof20.capture.plan import check_workspace, describe, estimate_duration, session_info
from tdof20.capture.runner import CaptureSummary, run_capture, verify_session

__all__ = ["CaptureConfig", "config_from_dict", "load_config", "sim_config", "check_workspace", "describe",
           "estimate_duration", "session_info", "CaptureSummary", "run_capture", "verify_session"]
