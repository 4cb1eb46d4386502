"""USD export of Gaussian worlds and episodes (``export_stage``) and the matching reader
(``read_stage``); see ``dsg_gym.usd.stage`` for the stage layout and docs/usd.md."""

from dsg_gym.usd.cameras import UsdCamera, cameras_from_arrays
from dsg_gym.usd.episode import Episode, EpisodeRecorder
from dsg_gym.usd.stage import StageContents, StageObject, UsdObject, export_stage, read_stage
from dsg_gym.usd.validate import ValidationIssue, validate_stage

__all__ = [
    "Episode",
    "EpisodeRecorder",
    "StageContents",
    "StageObject",
    "UsdCamera",
    "UsdObject",
    "ValidationIssue",
    "cameras_from_arrays",
    "export_stage",
    "read_stage",
    "validate_stage",
]
