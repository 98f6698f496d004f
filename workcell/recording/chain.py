"""The chain of recordings a resumed campaign makes: `campaign --resume OLD --out NEW` records
only the poses measured after the resume into NEW, whose session's `chained_from` {path, sha256,
samples} names OLD (the path relative to NEW's folder); a resume of a resume chains further.

`follow_chain` walks such a chain back from its newest file (each link's sha256 checked); the
resume (`workcell.campaign.resume.read_chain`) and every estimation (`load_chain`, through
`Dataset.from_recording`) read it here, so that the poses of every file of the chain are used
and a link missing or changed is never silently dropped.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from workcell.errors import UserError
from workcell.recording.reader import Recording, RecordingError, read_recording

if TYPE_CHECKING:
    import argparse

MAX_CHAIN = 1000  # links followed back; a longer chain is refused (a loop made by hand?)
CHAIN_OPTION = "--chain-missing"
CHAIN_MISSING = ("refuse", "ignore")


def file_sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(Path(path), "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def link_candidates(path: str, named_by: Path) -> list[Path]:
    """Where the file a `chained_from.path` names may be: relative to the file that names it
    (how workcell records it), as given (recordings made before, relative to the folder the
    resume ran in), or beside the file that names it (the two moved together)."""
    p = Path(path)
    cands = [p] if p.is_absolute() else [named_by.parent / p, p]
    cands.append(named_by.parent / p.name)
    seen, out = set(), []
    for c in cands:
        key = str(c.resolve()) if c.exists() else str(c)
        if key not in seen:
            seen.add(key)
            out.append(c)
    return out


def chain_link(rec: Recording, named_by: Path) -> tuple[Path | None, str | None, dict]:
    """The file `rec`'s `chained_from` names: (path, None) when found with the recorded sha256,
    (None, why) when it is missing or has changed, (None, None) when `rec` continues nothing.
    Third: the `chained_from` block."""
    link = rec.session.get("chained_from")
    if not link:
        return None, None, {}
    if not isinstance(link, dict) or not isinstance(link.get("path"), str) or not link["path"]:
        return None, f"{named_by}: its chained_from block names no file", {}
    want = link.get("sha256")
    cands = link_candidates(link["path"], named_by)
    found = [c for c in cands if c.is_file()]
    for c in found:
        if not isinstance(want, str) or file_sha256(c) == want.lower():
            return c, None, link
    n = link.get("samples")
    held = f" ({n} samples)" if isinstance(n, int) and not isinstance(n, bool) else ""
    if not found:
        why = f"{named_by} continues {link['path']}{held}, which is not at {cands[0]}"
    else:
        why = (
            f"{named_by} continues {found[0]}{held}, but that file has changed since (its sha256 "
            f"is not the one {named_by.name} recorded)"
        )
    return None, why, link


def follow_chain(newest: Recording, *, streams: bool = True) -> tuple[list[Recording], str, dict]:
    """The recordings of `newest`'s resume chain, oldest first, ending with `newest`; why the
    chain stops short ("" when it does not: a link missing or changed, which the caller refuses
    or accepts) and that link's `chained_from` block. A loop is refused in one line."""
    chain = [newest]
    named_by, rec = Path(newest.path), newest
    seen = {str(named_by.resolve())}
    while True:
        path, why, link = chain_link(rec, named_by)
        if why is not None:
            return chain[::-1], why, link
        if path is None:
            return chain[::-1], "", {}
        key = str(path.resolve())
        if key in seen or len(chain) >= MAX_CHAIN:
            raise UserError(
                f"{named_by}: its chained_from links lead back to {path} again (edited by "
                "hand?); cannot tell which poses were measured"
            )
        seen.add(key)
        rec = read_recording(path, streams=streams)
        chain.append(rec)
        named_by = path


@dataclass
class Chain:
    """The recordings an estimation uses: oldest first, the file it was asked for last."""

    recordings: list[Recording]
    sha256: list[str] = field(default_factory=list)  # of each file, in the same order
    notes: list[str] = field(default_factory=list)  # where the chain was cut, and why

    @property
    def newest(self) -> Recording:
        return self.recordings[-1]

    @property
    def samples(self) -> list[dict]:
        """Every file's samples, in the order of measurement (a resume's log times and sample
        indices continue the chain's)."""
        return [s for r in self.recordings for s in r.samples]

    def files(self) -> list[dict]:
        """{path (absolute), sha256, samples} of each file, oldest first: a model's provenance."""
        return [
            {"path": os.path.abspath(r.path), "sha256": h, "samples": len(r.samples)}
            for r, h in zip(self.recordings, self.sha256, strict=True)
        ]

    def line(self) -> str:
        """'b.mcap continues a.mcap: 11 + 34 poses'; '' for a single file."""
        if len(self.recordings) < 2:
            return ""
        older = ", ".join(r.path.name for r in self.recordings[:-1])
        counts = " + ".join(str(len(r.samples)) for r in self.recordings)
        return f"{self.newest.path.name} continues {older}: {counts} poses"


def _remeasured(chain: list[Recording], link: dict) -> str:
    """The file of `chain` that was resumed with --remeasure-missing when the file `link` names
    was already lost (its `chain` warning names that file): its poses were measured again there,
    so the chain ends at that link by the operator's choice. '' when none was."""
    name = Path(str(link.get("path") or "")).name
    if not name:
        return ""
    for r in chain:
        for e in r.events:
            if (
                e.get("kind") == "chain"
                and e.get("level") == "warning"
                and name in str(e.get("message") or "")
            ):
                return r.path.name
    return ""


def load_chain(rec: Recording | str | os.PathLike, *, missing: str = "refuse") -> Chain:
    """The chain of recordings an estimation of `rec` uses (`follow_chain`, streams not
    decoded). A link missing or changed is refused in one line naming it, unless `missing` is
    "ignore" or a later file of the chain measured its poses again (a resume with
    --remeasure-missing): the chain then ends there and a note says so."""
    if missing not in CHAIN_MISSING:
        raise UserError(
            f"{CHAIN_OPTION} must be one of {', '.join(CHAIN_MISSING)}, not {missing!r}"
        )
    if not isinstance(rec, Recording):
        rec = read_recording(rec, streams=False)
    recs, why, link = follow_chain(rec, streams=False)
    notes = []
    if why:
        again = _remeasured(recs, link)
        if again:
            notes.append(
                f"{why}; its poses were measured again in {again} (resumed with "
                "--remeasure-missing): the chain's files from there on are used"
            )
        elif missing == "ignore":
            notes.append(
                f"{why}; its poses (and any before it in the chain) are left out "
                f"({CHAIN_OPTION} ignore)"
            )
        else:
            raise RecordingError(
                f"{why}: its poses belong to this campaign; put the original back there, or "
                f"leave them out with `{CHAIN_OPTION} ignore` (fit, diagnose, replay)"
            )
    sha = [file_sha256(r.path) for r in recs]
    return Chain(recs, sha, notes)


def add_chain_option(p: argparse.ArgumentParser) -> None:
    """The option of the commands that estimate from a recording (fit, diagnose, replay)."""
    p.add_argument(
        CHAIN_OPTION,
        choices=CHAIN_MISSING,
        default="refuse",
        help="a resumed recording is used with every file it continues (its chained_from "
        "chain); when one of those is missing or changed: refuse (default), or ignore it and "
        "use the files after it",
    )
