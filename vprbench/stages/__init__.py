"""Post-retrieval stages: re-ranking and sequence matching, as plugins (see docs/stages.md)."""
from .base import TRACKS, Candidates, RerankOptions, Stage, StageContext, StageOptions, check_candidates
from .registry import ENTRY_POINT_GROUP, available_stages, create_stage, register_stage, stage_entry

__all__ = ["TRACKS", "Candidates", "RerankOptions", "Stage", "StageContext", "StageOptions", "check_candidates",
           "ENTRY_POINT_GROUP", "available_stages", "create_stage", "register_stage", "stage_entry"]
