"""Where a run writes: the MCAP and Rerun files under temporary names, renamed into place together.

Both files are written as ``.<name>.<run>.partial`` beside their final names (``<run>``
unique to the run) and renamed into place (``os.replace``) only when both are
complete, so an interrupted or failed run never leaves a truncated file under a final
name, and replaces existing outputs only then. A lock on ``.<session>.lock`` in the
output folder keeps a second run of the same session out while one writes; the run
that holds it removes what dead runs left behind.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import uuid
from pathlib import Path

from ..errors import OutputError, refuse_link_to_nothing, refuse_unexpanded_home
from ..record.commit_marker import killed_commits, marker_path, marker_run
from ..session.folder import check_utf8_path

log = logging.getLogger(__name__)


def _display(path: Path) -> str:
    """``path`` as printable text (bytes that are not UTF-8 shown as U+FFFD)."""
    return os.fsencode(path).decode("utf-8", "replace")


class OutputTarget:
    """Where one run writes ``<out_dir>/<name>.mcap`` and ``.rrd``: their temporary names,
    the lock that keeps other runs of the session out, the folders this run created.

    Made by :func:`prepare_outputs`; :meth:`commit` puts the pair in place,
    :meth:`release` removes the lock (and, after a failure, the folders it created
    if they are still empty).
    """

    def __init__(self, out_dir: Path, name: str, created: list[Path]) -> None:
        self.out_dir, self.name = out_dir, name
        self.mcap_path, self.rrd_path = out_dir / f"{name}.mcap", out_dir / f"{name}.rrd"
        self.run = f"{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self._created = created
        self._lock_path = lock_path(out_dir, name)
        self._lock_fd: int | None = None

    @property
    def finals(self) -> tuple[Path, Path]:
        return self.mcap_path, self.rrd_path

    def partial(self, path: Path) -> Path:
        """This run's temporary name for the final ``path``."""
        return path.with_name(f".{path.name}.{self.run}.partial")

    def _backup(self, path: Path) -> Path:
        return path.with_name(f".{path.name}.{self.run}.old")

    def file_names(self) -> list[str]:
        """Every name the run may give a file in the folder: the outputs, their temporary
        and backup names, the commit marker and the lock."""
        paths = [*self.finals, *map(self.partial, self.finals), *map(self._backup, self.finals)]
        paths += [marker_path(self.out_dir, self.name, self.run), self._lock_path]
        return [p.name for p in paths]

    def lock(self) -> None:
        """Take the session's lock in the folder, or raise OutputError if another run has it."""
        if self._lock_path.is_dir():
            raise OutputError(
                f"{_display(self._lock_path)}: is a folder where a run keeps its lock; remove it, "
                "or give this run another --out"
            )
        while True:
            fd = os.open(self._lock_path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise OutputError(
                    f"another run is writing {self.name} in {_display(self.out_dir)}; wait for it to "
                    "finish, or give this run another --out"
                ) from None
            # The previous holder removes the file as it lets go: a lock on a removed file
            # is no lock, so check that the file is still the one at the path.
            try:
                if os.path.samestat(os.fstat(fd), os.stat(self._lock_path)):
                    break
            except FileNotFoundError:
                pass
            os.close(fd)
        self._lock_fd = fd
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._finish_killed_commits()
        self._remove_stale()

    def _finish_killed_commits(self) -> None:
        """Put in place the rest of a pair whose run was killed between its renames (SIGKILL,
        power loss), as that run would have: its temporary files are complete by then, so
        the folder holds its new pair, not a new .mcap beside an old .rrd."""
        for marker in killed_commits(self.out_dir, self.name):
            run = marker_run(marker, self.name)
            for final in self.finals:
                partial = final.with_name(f".{final.name}.{run}.partial")
                if partial.exists():
                    os.replace(partial, final)
            _sync_folder(self.out_dir)
            marker.unlink()
            log.warning(
                "%s, %s: the run that wrote them was killed while putting them in place; "
                "put in place now, both are that run's",
                _display(self.mcap_path),
                self.rrd_path.name,
            )

    def _remove_stale(self) -> None:
        """Remove the temporary files of this session's earlier runs: with the lock held,
        no run is writing them (they died: SIGKILL, power loss)."""
        prefixes = tuple(f".{p.name}." for p in self.finals)
        for entry in os.scandir(self.out_dir):
            if entry.name.startswith(prefixes) and entry.name.endswith((".partial", ".old")):
                with contextlib.suppress(OSError):
                    os.unlink(entry.path)
                    log.debug("removed %s, left by a run that did not finish", entry.path)

    def commit(self) -> None:
        """Rename both temporary files into place: afterwards the folder holds the new pair,
        or, if a rename fails, the old pair (or none) as before.

        A marker file names the run while it renames, so that if it is killed between the
        two renames, the next run of the session in the folder puts the rest in place
        (:meth:`lock`), and :func:`pipeline.record.load.load_recording` warns meanwhile."""
        backups: list[tuple[Path, Path]] = []
        placed: list[Path] = []
        marker = marker_path(self.out_dir, self.name, self.run)
        try:
            for final in self.finals:
                if final.exists():
                    backup = self._backup(final)
                    try:
                        os.link(final, backup)  # the old file stays in place meanwhile
                    except OSError:  # a file system without hard links
                        os.replace(final, backup)
                    backups.append((final, backup))
            marker.touch(exist_ok=False)
            _sync_folder(self.out_dir)  # on disk before any rename
            for final in self.finals:
                os.replace(self.partial(final), final)
                placed.append(final)
            _sync_folder(self.out_dir)
            marker.unlink()
        except BaseException:
            with contextlib.suppress(OSError):
                marker.unlink()  # the old pair goes back: nothing for a later run to finish
            restored = dict(backups)
            for final in placed:
                with contextlib.suppress(OSError):
                    if final in restored:
                        os.replace(restored.pop(final), final)
                    else:
                        final.unlink()
            for final, backup in restored.items():  # moved aside but not yet replaced
                with contextlib.suppress(OSError):
                    if not final.exists():
                        os.replace(backup, final)
            raise
        finally:
            for _, backup in backups:
                with contextlib.suppress(FileNotFoundError):
                    backup.unlink()

    def release(self, *, failed: bool) -> None:
        """Let go of the lock; after a failure, remove the folders this run created if empty."""
        if self._lock_fd is not None:
            with contextlib.suppress(OSError):
                self._lock_path.unlink()  # while still held: see lock()
            os.close(self._lock_fd)
            self._lock_fd = None
        if failed:
            for folder in reversed(self._created):  # deepest first
                with contextlib.suppress(OSError):
                    folder.rmdir()


def _sync_folder(folder: Path) -> None:
    """Write ``folder``'s entries (created, renamed files) to disk, where the system can."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def lock_path(out_dir: Path, name: str) -> Path:
    """The file whose lock a run named ``name`` holds in ``out_dir`` while it writes there."""
    return out_dir / f".{name}.lock"


def prepare_outputs(out_dir: Path, name: str, force: bool) -> OutputTarget:
    """Check, before any work, that the outputs can be written, and take the folder's lock
    for ``name``. Call :meth:`OutputTarget.release` when the run ends."""
    check_utf8_path(out_dir, "choose an --out path in UTF-8", OutputError)
    refuse_unexpanded_home(out_dir, "--out")
    try:
        refuse_link_to_nothing(out_dir, "--out")
        for folder in (out_dir, *out_dir.parents):
            if folder.exists() and not folder.is_dir():
                where = "" if folder == out_dir else f" (in {out_dir})"
                raise OutputError(f"{folder}: is a file, not a directory{where}; give --out a directory")
        created = [f for f in (out_dir, *out_dir.parents) if not f.exists() and not f.is_symlink()][::-1]
    except PermissionError as exc:
        raise OutputError(
            f"{exc.filename or out_dir}: cannot be opened (permission denied); give --out a folder "
            "this user can write in"
        ) from None
    target = OutputTarget(out_dir, name, created)
    _check_name_lengths(target)
    try:
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(
                f"{out_dir}: cannot create the output directory ({exc.strerror}); give --out a folder "
                "this user can write in"
            ) from None
        if not os.access(out_dir, os.W_OK):
            raise OutputError(f"{out_dir}: output directory is not writable; use --out to choose another")
        try:
            target.lock()
        except OSError as exc:
            raise OutputError(
                f"{out_dir}: cannot write in the output directory ({exc.strerror}); give --out a folder "
                "this user can write in"
            ) from None
        for path in target.finals:
            # --force replaces recordings, not a folder (or a device) under their name.
            if path.exists() and not path.is_file():
                raise OutputError(f"{path}: is not a file but is where the recording goes; move it away")
            if path.exists() and not force:
                raise OutputError(f"{path}: already exists; use --force to replace it")
    except BaseException:
        target.release(failed=True)
        raise
    return target


def _check_name_lengths(target: OutputTarget) -> None:
    """Every file name the run will use fits the file system's limit (``NAME_MAX``), checked
    before any work: a session folder's name of 230 characters or more leaves no room for
    the temporary files' suffixes, which are needed only once every frame is processed."""
    folder = target.out_dir
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        limit = os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        limit = 255
    longest = max(len(os.fsencode(name)) for name in target.file_names())
    if longest > limit:
        raise OutputError(
            f"{target.name}: the session's name is too long for its output files' names "
            f"({longest} bytes, the file system takes {limit}); rename the session folder "
            f"to {len(os.fsencode(target.name)) - (longest - limit)} bytes or fewer"
        )


def output_error(out_dir: Path, exc: OSError) -> OutputError:
    if exc.errno == errno.ENOSPC:
        return OutputError(f"{out_dir}: disk full while writing the recordings; free space and rerun")
    return OutputError(f"{out_dir}: cannot write the recordings ({exc.strerror or exc})")
