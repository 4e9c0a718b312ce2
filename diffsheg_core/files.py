"""Writing files without losing what was there.

Every file the project writes goes through `atomic_write`: into a temporary file beside
the target, renamed over it only once complete, so a full disk, a crash or Ctrl-C leaves
the previous file byte for byte. `check_outputs` refuses, before any work is done, output
paths that cannot work: a folder, an input of the same run, two outputs on one file, a
symbolic link loop, or a place that cannot be written. `resolve_path` follows a user's path
to where it leads, refusing a loop of symbolic links with a message instead of a traceback.
"""

from __future__ import annotations

import errno
import os
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Iterable, Iterator, Optional, Union

from .errors import DiffshegError

PathLike = Union[str, os.PathLike]


def resolve_path(path: PathLike, what: str = "path", error: type[DiffshegError] = DiffshegError) -> Path:
    """`path` (~ expanded) made absolute with its symbolic links followed (the part that does
    not exist yet kept as given); `error` naming `what` ("output", "audio file", ...) where the
    path leads into a loop of symbolic links."""
    path = Path(path).expanduser()
    try:
        resolved = path.resolve()
    except RuntimeError:  # Python 3.11 and 3.12: "Symlink loop from ..."
        raise _loop(path, what, error) from None
    except OSError as exc:  # a link that cannot be read
        if exc.errno == errno.ELOOP:
            raise _loop(path, what, error) from None
        return path.absolute()
    try:
        resolved.stat()  # Python 3.13 resolves a loop without a word: stat meets it
    except OSError as exc:  # missing (an output to be), or unreadable: the callers' checks say so
        if exc.errno == errno.ELOOP:
            raise _loop(path, what, error) from None
    return resolved


def _loop(path: Path, what: str, error: type[DiffshegError]) -> DiffshegError:
    if path.is_symlink():
        return error(f"{what} '{path}' is a symbolic link that leads back to itself (directly or through "
                     "other links, a loop): point it at a real file, or give another path")
    return error(f"{what} '{path}' goes through a symbolic link that leads back to itself (a loop): point "
                 "that link at a real folder, or give another path")


def _same_file(a: Path, b: Path) -> bool:
    """Whether `a` and `b` name one file; False where either leads into a symbolic link loop
    (no file is there: the input's own check names the loop)."""
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and os.path.samefile(a, b))
    except (OSError, RuntimeError):  # RuntimeError: a symbolic link loop (Python 3.11, 3.12)
        return False


def check_output(path: PathLike, inputs: Iterable[Optional[PathLike]] = ()) -> Path:
    """`path` as a Path, if a file can be written there without harming an input; else a
    DiffshegError naming the problem and the fix."""
    path = Path(path).expanduser()
    resolve_path(path, "output")
    if path.is_dir():
        raise DiffshegError(f"output '{path}' is a folder: give a file name, e.g. {path / 'motion.npz'}")
    if path.exists() and not path.is_file():
        raise DiffshegError(f"output '{path}' exists and is not a regular file (a device, pipe or "
                            "socket): choose a file name")
    for source in inputs:
        if source is not None and _same_file(path, Path(source).expanduser()):
            raise DiffshegError(f"output '{path}' is an input of this run: writing it would destroy "
                                "the input; choose another output name")
    folder = path.parent
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir():
        raise DiffshegError(f"output '{path}': '{folder}' is a file, not a folder: choose another path")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise DiffshegError(f"output '{path}': the folder '{folder}' is not writable: check its "
                            "permissions or choose another folder")
    return path


def check_outputs(outputs: Iterable[Optional[PathLike]], inputs: Iterable[Optional[PathLike]] = ()
                  ) -> list[Path]:
    """`check_output` for each output given (None: not asked for); two on one file are refused."""
    inputs = list(inputs)
    checked: list[Path] = []
    for output in outputs:
        if output is None:
            continue
        path = check_output(output, inputs)
        if any(_same_file(path, other) for other in checked):
            raise DiffshegError(f"output '{path}' is named twice: give each output its own file")
        checked.append(path)
    return checked


@contextmanager
def atomic_write(path: PathLike, mode: str = "wb", encoding: Optional[str] = None,
                 newline: Optional[str] = None) -> Iterator[IO]:
    """Open a temporary file beside `path` for writing; when the block ends without an
    exception, it replaces `path`. On any failure the temporary file is removed and `path`
    is left as it was; an OSError (a full disk, a lost drive) becomes a DiffshegError naming
    `path`."""
    path = check_output(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)  # the umask applies
        with os.fdopen(fd, mode, encoding=encoding, newline=newline) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise DiffshegError(f"'{path}' could not be written ({exc.strerror or exc}); any file that "
                            "was there is unchanged: free some disk space or choose another folder") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
