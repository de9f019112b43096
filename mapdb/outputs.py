"""Writing output files safely: never over an input, always whole or not at all.

Every command that writes a file goes through this module:

* :func:`check_outputs` runs before any work and refuses an output that is one of the inputs (same
  device and inode, so symlinks and hard links are seen through), an output given twice, and an
  output that exists but is not a regular file (a FIFO would block the command, a directory cannot be
  replaced).  Character devices such as ``/dev/null`` are accepted and written straight to.
* :func:`atomic_path` / :func:`atomic_open` write to a hidden temporary file beside the target and
  rename it into place at the end, so a failure or a kill leaves the previous file intact.  Errors
  name the path the user gave, never the temporary name.
* :func:`refuse_existing` is the ``--overwrite`` rule: an existing output is replaced only when asked
  (every command of the CLI, through ``check_outputs(..., overwrite=...)``); never an input, even then.
* An output in a directory that does not exist is refused, as GDAL does (``OUT: directory DIR does
  not exist``), unless the caller asks for missing directories to be made (``parents``, the CLI's
  ``--parents``, like ``mkdir -p``).
* :class:`~mapdb.progress.Progress` (how long library functions report to the user) lives in
  :mod:`mapdb.progress`.

Symlinked outputs are written through: the link stays and its target is replaced, as GDAL and
rasterio do when they open an output path.
"""

from __future__ import annotations

import json
import math
import os
import re
import secrets
import shutil
import stat
import sys
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

from .errors import MapdbError, MapdbIOError, OutputClashError, OutputExistsError

__all__ = [
    "atomic_open",
    "atomic_path",
    "check_outputs",
    "creation_time",
    "dumps_strict",
    "json_line",
    "json_safe",
    "output_errors",
    "pid_alive",
    "refuse_existing",
    "remove_stale_temporaries",
    "temporary_prefix",
]

PathLike = str | os.PathLike[str]

# Long names are cut in the temporary name so that the extra ~30 characters never make it exceed
# the usual 255-byte limit of a file name.
_NAME_KEEP = 180


def _given(paths: Iterable[PathLike | None]) -> list[str]:
    """The paths that name files ("-" is stdin/stdout and None is "not given")."""
    return [os.fspath(p) for p in paths if p is not None and os.fspath(p) != "-"]


def _identity(path: str) -> tuple[int, int] | None:
    """(device, inode) of what ``path`` leads to, or None when there is nothing there yet."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISSOCK(mode):
        return "a socket"
    if stat.S_ISBLK(mode):
        return "a block device"
    return "not a regular file"


def _check_writable_place(out: str, parents: bool = False) -> None:
    """Refuse an output whose existing kind, or whose directory, makes writing impossible.

    ``parents``: a missing directory is fine (it will be made) if its nearest existing ancestor is one.
    """
    try:
        st = os.stat(out)
    except FileNotFoundError:
        st = None
    except OSError as exc:  # a parent that is a regular file (ENOTDIR), a symlink loop, ...
        raise MapdbIOError(f"{out}: cannot write ({exc.strerror or exc})") from None
    if st is not None:
        if not (stat.S_ISREG(st.st_mode) or stat.S_ISCHR(st.st_mode)):
            raise MapdbIOError(f"{out}: is {_kind(st.st_mode)}; an output must be a regular file")
        return
    parent = Path(os.path.realpath(out)).parent
    if not parents and not parent.exists():
        # As GDAL: a typo in a directory name is an error, not a new directory somewhere unexpected.
        shown = str(parent) if os.path.islink(out) else (os.path.dirname(out) or ".")
        raise MapdbIOError(f"{out}: directory {shown} does not exist")
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise MapdbIOError(f"{out}: cannot write ({parent} is not a directory)")


def _make_parent(out: str) -> None:
    """Create the missing directories above ``out`` (``mkdir -p``)."""
    try:
        Path(os.path.realpath(out)).parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MapdbIOError(f"{out}: cannot create its directory ({exc.strerror or exc})") from None


def check_outputs(outputs: Iterable[PathLike | None], inputs: Iterable[PathLike | None], *,
                  parents: bool = False, overwrite: bool = True, what: str = "file") -> None:
    """Refuse outputs that would destroy an input or cannot be written, before any work is done.

    The checks, in order: no output is an input (whatever ``overwrite``), nor another output; each is a
    regular file, a character device or nothing yet, in a directory that exists (or will, ``parents``);
    without ``overwrite`` none exists; then a file can be created beside each (a read-only folder is
    refused here, naming the output, rather than when the temporary file is made).

    Parameters
    ----------
    outputs, inputs : iterables of str, Path or None
        ``None`` and ``"-"`` (stdin/stdout) are ignored.
    parents : bool
        Create the outputs' missing directories (as ``mkdir -p``), once every check has passed.  Without
        it an output in a directory that does not exist is refused.
    overwrite : bool
        Whether existing outputs may be replaced (the CLI's ``--overwrite``).  Character devices
        (``/dev/null``) are never refused.
    what : str
        What the outputs are, for the refusal: ``"OUT: exists; pass --overwrite to replace this WHAT"``.

    Raises
    ------
    OutputClashError
        If an output is the same file as an input (compared by device and inode when both exist,
        by resolved path otherwise), or the same output is given twice.
    OutputExistsError
        If an output exists and ``overwrite`` is false.
    MapdbIOError
        If an output exists and is not a regular file or a character device (a FIFO, a directory, a
        socket), lies under a path that is not a directory, or (without ``parents``) in a directory
        that does not exist: ``"OUT: directory DIR does not exist"``; or if no file can be created in
        its directory: ``"OUT: cannot write (Read-only file system)"``.

    Examples
    --------
    >>> import os, tempfile
    >>> d = tempfile.mkdtemp(); src = os.path.join(d, "a.osm"); open(src, "w").close()
    >>> os.symlink(src, os.path.join(d, "link"))
    >>> check_outputs([os.path.join(d, "b.mapdb")], [src])
    >>> check_outputs([os.path.join(d, "link")], [src])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    mapdb.errors.OutputClashError: .../link: is the same file as input .../a.osm; choose another output path
    >>> check_outputs([os.path.join(d, "new", "b.mapdb")], [src])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    mapdb.errors.MapdbIOError: .../new/b.mapdb: directory .../new does not exist
    >>> check_outputs([os.path.join(d, "new", "b.mapdb")], [src], parents=True)
    >>> os.path.isdir(os.path.join(d, "new"))
    True
    """
    outs = _given(outputs)
    ins = [(p, _identity(p), os.path.realpath(p)) for p in _given(inputs)]
    seen: dict[object, str] = {}
    for out in outs:
        ident, real = _identity(out), os.path.realpath(out)
        for name, in_ident, in_real in ins:
            if (ident is not None and ident == in_ident) or real == in_real:
                raise OutputClashError(f"{out}: is the same file as input {name}; choose another output path")
        _check_writable_place(out, parents)
        if _is_char_device(Path(real)):  # /dev/null may take any number of outputs
            continue
        for key in (ident, real):
            if key is not None and key in seen:
                raise OutputClashError(f"{out}: is the same file as output {seen[key]}; choose another output path")
        seen.update({k: out for k in (ident, real) if k is not None})
    for out in outs:
        refuse_existing(out, overwrite, what)
    for out in outs:
        if parents:
            _make_parent(out)
        _probe(out)


def _probe(out: str) -> None:
    """Create and delete a temporary file beside ``out``, as :func:`atomic_path` will: an error names ``out``."""
    target = Path(os.path.realpath(out))
    if _is_char_device(target):
        return
    probe = target.parent / f"{temporary_prefix(target)}{secrets.token_hex(4)}.tmp"
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o600))
    except OSError as exc:
        raise _write_error(out, exc) from None
    probe.unlink(missing_ok=True)


def refuse_existing(path: PathLike | None, overwrite: bool, what: str = "map") -> None:
    """Refuse to replace an existing file unless ``overwrite`` (the ``--overwrite`` rule).

    Raises
    ------
    OutputExistsError
        If ``path`` exists (a symlink counts when its target does) and ``overwrite`` is false.
        Character devices (``/dev/null``) and empty directories (an output folder made beforehand) hold
        nothing to lose and are never refused.
    """
    if path is None or os.fspath(path) == "-" or overwrite:
        return
    try:
        st = os.stat(path)
    except OSError:
        return
    if stat.S_ISCHR(st.st_mode) or (stat.S_ISDIR(st.st_mode) and _empty_directory(path)):
        return
    raise OutputExistsError(f"{os.fspath(path)}: exists; pass --overwrite to replace this {what}")


def _empty_directory(path: PathLike) -> bool:
    try:
        with os.scandir(path) as entries:
            return next(entries, None) is None
    except OSError:
        return False  # cannot see inside: the safe side is "it may hold something"


def temporary_prefix(target: Path) -> str:
    """The start of the name of this process's temporaries of ``target`` (``.NAME.PID.``), which
    :func:`remove_stale_temporaries` recognises once the process is gone."""
    return f".{target.name[:_NAME_KEEP]}.{os.getpid()}."


def _temp_pattern(target: Path) -> re.Pattern[str]:
    """Names of ``target``'s temporaries: files (``.NAME.PID.HEX.tmp[.ext]``) and the folders of records a
    streaming map writer spills (``.NAME.PID.XXXXXXXX.spill``, :class:`mapdb.mapfile.writer.MapWriter`)."""
    name = re.escape(target.name[:_NAME_KEEP])
    return re.compile(rf"\.{name}\.(\d+)\.(?:[0-9a-f]+\.tmp(?:\.[^.]*)?|[A-Za-z0-9_]+\.spill)")


def pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    except OSError:
        return True  # unknown: keep the file, the safe side
    return True


def remove_stale_temporaries(target: PathLike) -> int:
    """Delete temporary files (and spill folders) of ``target`` left by runs that were killed; return how many.

    A temporary file is stale when its name has this target's prefix and the process id embedded in
    it is no longer running.  (Another host writing into a shared directory, or a reused pid, can make
    a live file look stale or a stale one look live; the first only fails that other write, the
    second only leaves a file behind.)
    """
    target = Path(os.path.realpath(target))
    pattern = _temp_pattern(target)
    removed = 0
    try:
        names = os.listdir(target.parent)
    except OSError:
        return 0
    prefix = f".{target.name[:_NAME_KEEP]}."
    for name in names:
        match = pattern.fullmatch(name) if name.startswith(prefix) else None
        if match and not pid_alive(int(match.group(1))):
            stale = target.parent / name
            try:
                if name.endswith(".spill") and stale.is_dir() and not stale.is_symlink():
                    shutil.rmtree(stale)
                else:
                    os.unlink(stale)
                removed += 1
            except OSError:
                pass
    return removed


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # not every file system can sync a directory
        pass
    finally:
        os.close(fd)


def _write_error(path: PathLike, exc: OSError) -> MapdbIOError:
    return MapdbIOError(f"{os.fspath(path)}: cannot write ({exc.strerror or exc})")


def _is_char_device(path: Path) -> bool:
    try:
        return stat.S_ISCHR(os.stat(path).st_mode)
    except OSError:
        return False


@contextmanager
def atomic_path(path: PathLike, *, keep_suffix: bool = False, parents: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path``.

    The temporary file, ``.{name}.{pid}.{random}.tmp`` in the target's directory, is created empty
    (so its name is reserved) with the mode the umask gives a new file; the caller writes it, by
    name, however it likes (it may also delete and recreate it).  On a clean exit it is synced and
    renamed over ``path`` (symlinks are followed: the link's target is replaced); on an exception it
    is deleted and the exception propagates.  Temporary files of this target left by killed runs
    are removed first.  An existing character device
    (``/dev/null``) is yielded as is and written in place: a caller that deletes the yielded path
    before writing must check that it is a regular file.

    Parameters
    ----------
    path : str or Path
        The file to produce.
    keep_suffix : bool
        End the temporary name with ``path``'s suffix too (``...tmp.png``), for writers that choose
        a format from the file name (matplotlib).
    parents : bool
        Create missing parent directories (``mkdir -p``); without it a missing directory is an error.

    Raises
    ------
    MapdbIOError
        ``"PATH: directory DIR does not exist"`` (without ``parents``).
        ``"PATH: cannot write (reason)"`` when the temporary file cannot be created, written (an
        ``OSError`` without another file name raised in the block) or renamed; it names ``path``.
        A :class:`MapdbError` raised in the block that names the temporary file is raised again
        naming ``path``.
    """
    given = os.fspath(path)
    target = Path(os.path.realpath(given))
    if _is_char_device(target):
        with _naming_errors(given, target):
            yield target
        return
    with _naming_errors(given, None, every=True):
        _check_writable_place(given, parents)
        if parents:
            target.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(target)
        suffix = target.suffix if keep_suffix else ""
        tmp = target.parent / f"{temporary_prefix(target)}{secrets.token_hex(4)}.tmp{suffix}"
        # O_EXCL reserves the name; mode 0o666 lets the kernel apply the umask (and default ACLs).
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
        mode = stat.S_IMODE(os.fstat(fd).st_mode)
        os.close(fd)
    try:
        with _naming_errors(given, tmp):
            yield tmp
            _settle(tmp, mode)
            os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(target.parent)


def _temporaries_named(given: str) -> re.Pattern[str]:
    """Paths of the hidden temporaries beside ``given`` (files, folders, work folders, and what lies in them) as
    a writer's error names them: group 1 is the temporary's name, group 2 the path inside it."""
    target = Path(os.path.realpath(given))
    # Writers cut long names at 100 characters or more (_NAME_KEEP here): the first 100 are always kept.
    return re.compile(re.escape(f"{target.parent}{os.sep}") + "(" + re.escape(f".{target.name[:100]}")
                      + r"[^\s'\"/]*)(?:/([^\s'\"]*))?")


def _about(filename: Any, temporaries: re.Pattern[str], given: str, tmp: Path | None) -> bool:
    """Whether an OS error's file is the output: none given, the output itself or one of its temporaries."""
    if filename is None:
        return True
    name = os.fsdecode(filename)
    return name in (given, str(tmp)) or temporaries.match(os.path.realpath(name)) is not None


def _renamed(text: str, given: str, tmp: Path | None, temporaries: re.Pattern[str]) -> str:
    """``text`` naming ``given`` wherever it names a temporary of it.

    A file in a temporary folder (``.out.PID.X.tmp/analysis.png``) becomes that file in the output folder
    (``out/analysis.png``); a file in a writer's work folder (``.a.qidx.PID.X.build/bucket``) is the output.
    """
    if tmp is not None:
        text = text.replace(str(tmp), given)

    def one(match: re.Match[str]) -> str:
        inside = match.group(2)
        return os.path.join(given, inside) if inside and match.group(1).endswith(".tmp") else given

    return temporaries.sub(one, text)


@contextmanager
def _naming_errors(given: str, tmp: Path | None, every: bool = False) -> Iterator[None]:
    """Make errors of writing ``tmp`` (the temporary file, or a device written in place) name ``given``.

    ``every``: all OS errors are about the output (preparing its directory and temporary file).  Otherwise an
    OS error is about the output when it names no file, the output, or a temporary beside it (``tmp``, or a
    work folder a writer made with the same prefix); a :class:`MapdbError` or a writer's own error (GDAL's,
    SQLite's) whose message names such a temporary is raised again naming ``given``.
    """
    temporaries = _temporaries_named(given)

    def renamed(text: str) -> str:
        return _renamed(text, given, tmp, temporaries)

    try:
        yield
    except MapdbError as exc:
        if renamed(str(exc)) != str(exc):
            # a writer's own error names the file it was given: name the user's path instead
            raise type(exc)(renamed(str(exc))) from exc.__cause__
        raise
    except OSError as exc:
        if every or _about(exc.filename, temporaries, given, tmp):
            named = given if every or exc.filename is None else renamed(os.fsdecode(exc.filename))
            raise _write_error(named, exc) from None
        raise  # about another file (an input read in the block): its own message is right
    except Exception as exc:
        text = renamed(str(exc))
        if text == str(exc):
            raise  # not about the output
        raise MapdbIOError(text if text.startswith(given) else f"{given}: cannot write ({text})") from exc


@contextmanager
def output_errors(path: PathLike) -> Iterator[None]:
    """Make the errors of the block that are about ``path`` or its hidden temporaries name ``path``.

    For writers that make their own temporary beside an output (a folder written whole, a work folder):
    an ``OSError`` naming no file, or naming such a temporary, becomes ``"PATH: cannot write (reason)"``
    (a file inside a temporary folder is named inside ``path``), and a :class:`MapdbError` or another
    library's error (GDAL's, SQLite's) naming a temporary names ``path`` instead.

    Examples
    --------
    >>> import os, tempfile
    >>> d = tempfile.mkdtemp(); out = os.path.join(d, "out")
    >>> with output_errors(out):  # doctest: +ELLIPSIS
    ...     raise OSError(27, "File too large", os.path.join(d, ".out.1.ab.tmp", "analysis.png"))
    Traceback (most recent call last):
    mapdb.errors.MapdbIOError: .../out/analysis.png: cannot write (File too large)
    """
    with _naming_errors(os.fspath(path), None):
        yield


def _settle(tmp: Path, mode: int) -> None:
    """Sync the finished temporary file, with the mode it was created with (the umask's, or a default ACL's).

    A writer may have deleted and recreated it under its own mode: SQLite (GeoPackage) creates files
    with 0644 & ~umask, whatever the umask allows.
    """
    fd = os.open(tmp, os.O_RDONLY)
    try:
        if stat.S_IMODE(os.fstat(fd).st_mode) != mode:
            os.chmod(tmp, mode)
        os.fsync(fd)
    finally:
        os.close(fd)


def json_safe(value: Any) -> Any:
    """``value`` with every non-finite float (NaN, infinities) replaced by None, for strict JSON.

    Recurses into dicts, lists and tuples; numpy scalars become Python numbers.

    Examples
    --------
    >>> json_safe({"rms_m": float("nan"), "bounds": [1.0, float("inf")], "n": 3})
    {'rms_m': None, 'bounds': [1.0, None], 'n': 3}
    """
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str | int):
        return value
    if hasattr(value, "item") and callable(value.item) and getattr(value, "shape", None) == ():
        value = value.item()  # numpy scalar
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def json_line(value: Any) -> str:
    """``value`` as compact JSON (no spaces; ``NaN`` or ``Infinity`` refused with ValueError): one line of a stream.

    The same text as ``json.dumps(value, separators=(",", ":"), allow_nan=False)``, from one encoder made once:
    ``json.dumps`` with options other than its defaults builds an encoder every call (3-4 microseconds of each
    answer a ``mapdb query`` stream writes).

    Examples
    --------
    >>> json_line({"id": "a", "xy": [1.5, 2]})
    '{"id":"a","xy":[1.5,2]}'
    """
    return _COMPACT(value)


_COMPACT = json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode


def dumps_strict(value: Any, **kwargs: Any) -> str:
    """``json.dumps`` that never writes ``NaN`` or ``Infinity`` (RFC 8259): non-finite numbers become null."""
    return json.dumps(json_safe(value), allow_nan=False, **kwargs)


@contextmanager
def atomic_open(path: PathLike, mode: str = "w", encoding: str | None = "utf-8", **kwargs: Any) -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path`` for writing; on success it replaces ``path``.

    Like :func:`atomic_path`, yielding an open file.  ``"-"`` yields standard output (text or binary
    after ``mode``), which is flushed, not closed.  Errors while writing name ``path``.

    Examples
    --------
    >>> import os, tempfile
    >>> p = os.path.join(tempfile.mkdtemp(), "out.txt")
    >>> with atomic_open(p) as f:
    ...     _ = f.write("whole or nothing")
    >>> open(p).read()
    'whole or nothing'
    """
    if mode not in ("w", "wb", "wt"):
        raise ValueError(f"atomic_open writes a new file: mode must be 'w', 'wt' or 'wb', not {mode!r}")
    binary = "b" in mode
    if os.fspath(path) == "-":
        stream: IO[Any] = sys.stdout.buffer if binary else sys.stdout
        try:
            yield stream
            stream.flush()
        except OSError as exc:
            if isinstance(exc, MapdbError | BrokenPipeError):
                raise  # a reader that stopped reading (``| head``) is not an error to report: the CLI exits quietly
            raise MapdbIOError(f"<stdout>: cannot write ({exc.strerror or exc})") from None
        return
    with atomic_path(path) as tmp:
        if binary:
            f = open(tmp, mode, **kwargs)  # noqa: SIM115
        else:
            f = open(tmp, mode, encoding=encoding, **kwargs)  # noqa: SIM115
        with f:  # atomic_path syncs the file once it is closed
            yield f


def creation_time() -> str:
    """The time a file records as its writing: now, or ``SOURCE_DATE_EPOCH`` when set (reproducible files).

    Maps and quad indexes both record it, so that two builds of the same inputs with the variable set are
    byte-identical (https://reproducible-builds.org/specs/source-date-epoch/).
    """
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    when = datetime.fromtimestamp(int(epoch), UTC) if epoch.isdigit() else datetime.now(UTC)
    return when.isoformat(timespec="seconds")
