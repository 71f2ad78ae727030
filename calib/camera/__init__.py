"""The camera's intrinsics: lens models and their choice, bundle refinement, board views."""
