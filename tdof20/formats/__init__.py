"""Readers and atomic writers of the folders the stages exchange: the raw capture session
(:mod:`tdof20.formats.session`, its journal :mod:`tdof20.formats.journal`), BOP scenes
(:mod:`tdof20.formats.bop`), BOP object models (:mod:`tdof20.formats.bop_models`), the released
TDoF20 layout (:mod:`tdof20.formats.tdof20_release`) and the checked JSON/PNG primitives beneath
them (:mod:`tdof20.formats.io`, :mod:`tdof20.formats.checks`, :mod:`tdof20.formats.bop_json`).
See ``docs/formats.md``."""

from tdof20.formats.io import (
    atomic_write_bytes,
    check_output_dir,
    check_output_file,
    decode_png,
    dumps_json,
    encode_png,
    png_header,
    read_bytes,
    read_json,
    read_png,
    read_text,
    sha256_bytes,
    sha256_file,
    write_json,
    write_png,
)
from tdof20.formats.journal import JOURNAL_FILE, PHASES, JournalEntry, append_journal, frame_paths, read_journal
from tdof20.formats.session import (
    FORMAT,
    SESSION_FILE,
    TRUTH_DIR,
    ArmPosition,
    RawSession,
    SessionInfo,
    read_session,
    write_frame,
    write_session,
)
from tdof20.formats.bop_json import dumps_bop_json
from tdof20.formats.bop_models import (
    MODELS_INFO,
    model_path,
    read_model_mesh,
    read_models_info,
    write_model_mesh,
    write_models_info,
)
from tdof20.formats.bop import (
    EMPTY_BBOX,
    SCENE_CAMERA,
    SCENE_GT,
    SCENE_GT_INFO,
    BopScene,
    BopSceneWriter,
    bbox_from_mask,
    check_scene_images,
    gt_info_from_masks,
    pose_from_bop,
    pose_to_bop,
    read_scene,
)

__all__ = [
    # io
    "atomic_write_bytes", "check_output_dir", "check_output_file", "decode_png", "dumps_json", "encode_png",
    "png_header", "read_bytes", "read_json", "read_png", "read_text", "sha256_bytes", "sha256_file", "write_json",
    "write_png",
    # session
    "FORMAT", "JOURNAL_FILE", "PHASES", "SESSION_FILE", "TRUTH_DIR", "ArmPosition", "JournalEntry",
    "RawSession", "SessionInfo", "append_journal", "frame_paths", "read_journal", "read_session",
    "write_frame", "write_session",
    # bop
    "EMPTY_BBOX", "MODELS_INFO", "SCENE_CAMERA", "SCENE_GT", "SCENE_GT_INFO", "BopScene",
    "BopSceneWriter", "bbox_from_mask", "check_scene_images", "dumps_bop_json", "gt_info_from_masks", "pose_from_bop",
    "pose_to_bop", "read_models_info", "read_scene", "write_models_info", "model_path",
    "read_model_mesh", "write_model_mesh",
]
