"""Small CLI commands that belong to no stage: `body make-test-model` and `session import`
(kept out of :mod:`embodmocap.cli` so that module stays readable)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro


@dataclass(frozen=True)
class BodyMakeTestModel:
    """Generate the built-in body model (SMPL file layout; needs no licensed file)."""

    out: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")]
    """Output .npz path."""
    seed: int = 0
    """Random seed of the generated model (0 is the one the demo and tests use)."""

    def run(self) -> int:
        from embodmocap.body.testmodel import make_test_model_cli

        make_test_model_cli(self.out, seed=self.seed)
        print(f"wrote {self.out}")
        return 0


@dataclass(frozen=True)
class SessionImport:
    """Create session.toml from a CSV/XLSX sheet in the paper release's layout."""

    sheet: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SHEET")]
    """The .csv or .xlsx sheet (columns scene_folder, seq_name, in_door, v1_start, v2_start, ...)."""
    session: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SESSION")]
    """Session folder (relative scene folders are resolved against it)."""
    force: bool = False
    """Overwrite an existing session.toml."""
    capture_pattern: str = "{scene_folder}/{seq_name}/raw{index}"
    """Where each view's capture lives, relative to the session; placeholders {scene_folder},
    {scene}, {seq_name}, {view} (v1/v2) and {index} (1/2). The default is the release's layout."""
    contact_sheet: Path | None = None
    """For a CSV sheet: a second CSV with the `contact` table (columns scene, contacts)."""
    check: bool = True
    """Refuse to write a manifest whose capture folders are missing (--no-check writes it anyway)."""

    def run(self) -> int:
        from embodmocap.io.sheet_import import import_sheet_cli

        path = import_sheet_cli(
            self.sheet, self.session, capture_pattern=self.capture_pattern,
            contact_sheet=self.contact_sheet, force=self.force, check=self.check,
        )
        print(f"wrote {path}")
        return 0
