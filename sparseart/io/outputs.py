"""Outputs as one unit: ``--out`` is checked before any work, every output is written into a
temporary folder, and the whole set is moved into place at the end.

* :func:`check_out_dir` (before any work): ``--out`` must be a folder or creatable (its nearest
  existing ancestor a writable folder), writable, and neither the scene folder nor inside it.
* :class:`StagedOutputs`: a hidden temporary folder beside ``--out`` (inside it when ``--out``
  exists, so the final moves never cross a file system) receives every file; :meth:`commit`
  moves them in: a new ``--out`` is the renamed staging folder; into an existing one each entry
  replaces its namesake (old ones are moved aside first and put back if any move fails).
  On failure (an exception before or during the commit) the staging folder is removed: the old
  outputs stay untouched and no new ones appear.
* Files and folders get the permissions the umask allows (``0o666``/``0o777`` minus the umask),
  not ``mkstemp``'s private ``0o600``.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from sparseart.io.validate import one_line
from sparseart.types import SceneError

STAGING_PREFIX = ".sparseart-staging-"


def current_umask() -> int:
    """The process umask (read without changing it where /proc allows; else set and restored)."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def file_mode() -> int:
    return 0o666 & ~current_umask()


def folder_mode() -> int:
    return 0o777 & ~current_umask()


def _fail(path: Path, problem: str) -> SceneError:
    return SceneError(one_line(f"{path}: {problem}"))


def _nearest_existing(path: Path) -> Path:
    for candidate in (path, *path.parents):
        if os.path.lexists(candidate):
            return candidate
    return Path(".")


def _inside(child: Path, parent: Path) -> bool:
    return child == parent or parent in child.parents


def check_out_dir(out: str | Path, scene: str | Path | None = None) -> Path:
    """Check ``--out`` before any work; return it as a Path. Creates nothing.

    Raises:
        SceneError: ``--out`` is a file, not writable, not creatable, the scene folder or inside it.
    """
    out = Path(out)
    if str(out) == "":
        raise SceneError("--out: empty path")
    resolved = Path(os.path.realpath(out))
    if scene is not None:
        scene_resolved = Path(os.path.realpath(scene))
        if _inside(resolved, scene_resolved):
            raise _fail(out, "--out is the scene folder or inside it; write the results elsewhere")
    if os.path.lexists(out):
        if not out.is_dir():
            raise _fail(out, "--out exists and is not a folder")
        if not os.access(out, os.W_OK | os.X_OK):
            raise _fail(out, "--out folder is not writable")
        return out
    anchor = _nearest_existing(resolved.parent)
    if not anchor.is_dir():
        raise _fail(out, f"--out cannot be created: {anchor} is not a folder")
    if not os.access(anchor, os.W_OK | os.X_OK):
        raise _fail(out, f"--out cannot be created: {anchor} is not writable")
    return out


class StagedOutputs:
    """A temporary folder collecting every output of a run, moved into ``out`` by :meth:`commit`.

    Use as a context manager; leaving the block without :meth:`commit` (an exception) removes the
    staging folder. ``path`` is where writers put their files.
    """

    def __init__(self, out: str | Path, scene: str | Path | None = None) -> None:
        self.out = check_out_dir(out, scene)
        self.committed = False
        self._renamed = False   # the staging folder itself became ``out``
        if os.path.isdir(self.out):
            where = self.out
        else:
            where = _nearest_existing(Path(os.path.realpath(self.out)).parent)
        try:
            self.path = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=where))
            os.chmod(self.path, folder_mode())
        except OSError as error:
            raise _fail(self.out, f"--out: cannot write there ({error.strerror})") from None

    def __enter__(self) -> "StagedOutputs":
        return self

    def __exit__(self, kind, value, traceback) -> None:
        self.discard()

    def final(self, staged: str | Path) -> Path:
        """Where a file written under :attr:`path` ends up after :meth:`commit`."""
        return self.out / Path(staged).relative_to(self.path)

    def discard(self) -> None:
        """Remove the staging folder (idempotent; nothing to do once it became ``out``)."""
        if not self._renamed:
            shutil.rmtree(self.path, ignore_errors=True)

    def commit(self) -> None:
        """Move every staged entry into ``out`` (see the module docstring). On failure nothing
        new is left in ``out`` and the old entries are back in place.

        Raises:
            SceneError: the moves failed (``--out`` vanished, became unwritable, ...).
        """
        try:
            if not os.path.lexists(self.out):
                self.out.parent.mkdir(parents=True, exist_ok=True)
                try:
                    os.rename(self.path, self.out)
                    self.committed = self._renamed = True
                    return
                except OSError:
                    if not self.out.is_dir():  # something else appeared at out
                        raise
                    # created meanwhile: merge below (the staging folder is beside it, same file system)
            self._merge()
            self.committed = True
        except OSError as error:
            raise _fail(self.out, f"cannot move the outputs into --out ({error.strerror or error})") from None
        finally:
            if not self.committed:
                self.discard()

    def _merge(self) -> None:
        names = sorted(n for n in os.listdir(self.path))
        backup = Path(tempfile.mkdtemp(prefix=".previous-", dir=self.path))
        moved_aside: list[str] = []
        moved_in: list[str] = []
        try:
            for name in names:
                target = self.out / name
                if os.path.lexists(target):
                    os.rename(target, backup / name)
                    moved_aside.append(name)
                os.rename(self.path / name, target)
                moved_in.append(name)
        except OSError:
            for name in moved_in:   # roll back: new entries out, old ones back
                try:
                    os.rename(self.out / name, self.path / name)
                except OSError:
                    _remove(self.out / name)
            for name in moved_aside:
                try:
                    os.rename(backup / name, self.out / name)
                except OSError:
                    pass
            raise
        self.discard()


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        try:
            path.unlink()
        except OSError:
            pass
