"""Annotation: from a raw capture session to a labelled BOP scene (stages)."""

from tdof20.annotate.registration import (
    ArmRegistration,
    FrameRegistration,
    RegistrationConfig,
    RegistrationResult,
    evaluate_against_truth,
    register_session,
    truth_T_ref_frame,
)

__all__ = ["ArmRegistration", "FrameRegistration", "RegistrationConfig", "RegistrationResult",
           "evaluate_against_truth", "register_session", "truth_T_ref_frame"]
