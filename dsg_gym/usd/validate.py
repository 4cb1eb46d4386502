"""Run OpenUSD's registered validators (``pxr.UsdValidation``) over a stage.

usd-core ships no ``usdchecker`` binary; this is its library equivalent: every validator in the
``UsdValidation.ValidationRegistry`` (stage metadata, composition, attribute types, UsdGeom,
UsdPhysics rigid body / collider / joint checks, UsdShade, UsdSkel, ...) runs over the stage.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pxr import Sdf, Usd, UsdValidation

__all__ = ["ValidationIssue", "validate_stage"]


@dataclass(frozen=True)
class ValidationIssue:
    """One finding: ``severity`` (``"Error"``, ``"Warn"`` or ``"Info"``), validator, name, message."""

    severity: str
    validator: str
    name: str
    message: str
    sites: tuple[str, ...] = ()

    def __str__(self) -> str:
        where = f" at {', '.join(self.sites)}" if self.sites else ""
        return f"[{self.severity}] {self.validator}: {self.name}{where}: {self.message}"


def validate_stage(stage_or_path: Usd.Stage | str | Path) -> list[ValidationIssue]:
    """All findings of all registered validators on the stage (a ``Usd.Stage`` or a file path,
    opened fresh). An empty list, or one without ``severity == "Error"``, means it passed."""
    if isinstance(stage_or_path, Usd.Stage):
        stage = stage_or_path
    else:
        layer = Sdf.Layer.OpenAsAnonymous(str(stage_or_path))
        if layer is None:
            raise ValueError(f"validate_stage: cannot open {str(stage_or_path)!r}")
        stage = Usd.Stage.Open(layer)
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    issues = []
    for err in context.Validate(stage):
        if err.HasNoError():
            continue
        validator = err.GetValidator()
        sites = []
        for site in err.GetSites():
            if site.IsPrim() or site.IsProperty():
                sites.append(str(site.GetPrim().GetPath() if site.IsPrim() else site.GetProperty().GetPath()))
        issues.append(
            ValidationIssue(
                severity=str(err.GetType().name),
                validator=validator.GetMetadata().name if validator else "?",
                name=str(err.GetName()),
                message=err.GetMessage(),
                sites=tuple(sites),
            )
        )
    return issues
