"""``perchpose target``: the printable target at true scale, with a 100 mm scale bar."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from perchpose.app.inputs import load_target
from perchpose.target import TargetSpec


@dataclass(frozen=True)
class TargetOptions:
    """Where to write the sheet, the target YAML (None: the paper's), a PNG's resolution,
    where to write the target's own YAML as well (None: nowhere), and the page (``a4``,
    ``letter`` or ``fit``)."""

    out: str
    target_file: str | None = None
    dpi: int = 600
    save_spec: str | None = None
    paper: str = "a4"


@dataclass(frozen=True)
class TargetSheet:
    """The sheet written and the target on it."""

    path: Path
    spec: TargetSpec


def run(options: TargetOptions) -> TargetSheet:
    """Write the target sheet (and its YAML where asked)."""
    from perchpose.printable import write_target_sheet

    spec = load_target(options.target_file)
    path = write_target_sheet(spec, options.out, dpi=options.dpi, paper=options.paper)
    if options.save_spec:
        spec.save(options.save_spec)
    return TargetSheet(path, spec)
