"""The one policy of every command that writes an output (a recording, a results folder, a
calibration, a capture, certificates, figures): no existing output is replaced unless the command is
given ``--force``, and no folder is made but the output's own, the folder its files go
into, when that folder's parent exists (``--record out/lab.mcap`` makes ``out/``;
``--record /no/such/dir/x.mcap`` is refused in one line, never a chain of folders)."""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator

from .errors import OutputExists, ReplayError

#: what a refusal tells the user to do
FORCE_HINT = "--force replaces it"


def own_folder(folder: str | Path, output: str | Path | None = None) -> Path:
    """The folder an output (``output``, named in the errors; else the folder) goes into, made
    if missing when its parent exists; a ReplayError naming the missing parent otherwise
    (qradar makes the output's own folder only)."""
    folder = Path(folder)
    if folder.is_dir():
        return folder
    what = f"cannot write {output}" if output is not None else f"cannot write into {folder}"
    if os.path.lexists(folder):
        raise ReplayError(f"{what}: {folder} is not a folder")
    parent = folder.parent
    if not parent.is_dir():
        raise ReplayError(f"{what}: {parent} does not exist (qradar makes only its output's own folder, never the "
                          f"folders above it: create {parent} first)")
    try:
        folder.mkdir(exist_ok=True)
    except OSError as exc:
        raise ReplayError(f"{what}: cannot create the folder {folder}: {exc.strerror or exc}") from None
    return folder


def check_not_input(path: str | Path, inputs: Iterable[str | Path | None], what: str = "output") -> None:
    """A ReplayError when the output ``path`` is one of the command's ``inputs`` (the same file,
    by any name; None: none given): ``--force`` replaces an earlier output, never what the
    command reads."""
    for src in inputs:
        if src is None or not os.path.lexists(src) or not os.path.lexists(path):
            continue
        if os.path.samefile(src, path):  # by any name: a link, a relative path
            raise ReplayError(f"{what} {path} is also this command's input {src}: give the output another name "
                              "(--force replaces an earlier output, never an input)")


def check_file_kind(path: str | Path, what: str = "output") -> Path:
    """A ReplayError when the output ``path`` is a folder, or a symbolic link (``--force`` or
    not: writing through it would replace the file it points to, which qradar did not make)."""
    path = Path(path)
    if path.is_symlink():
        raise ReplayError(f"{what} {path} is a symbolic link (to {os.readlink(path)}): qradar writes no output "
                          "through a link, which would replace the file it points to; remove the link or choose "
                          "another name")
    if path.is_dir():
        raise ReplayError(f"{what} {path} is a folder, not a file")
    return path


def check_new_file(path: str | Path, force: bool = False, what: str = "output",
                   inputs: Iterable[str | Path | None] = ()) -> Path:
    """A file about to be written: an existing one is refused unless ``force`` (an
    OutputExists naming it), a folder or a link always (:func:`check_file_kind`), one of the
    command's ``inputs`` even with ``force`` (:func:`check_not_input`); its own folder made
    (:func:`own_folder`)."""
    check_not_input(path, inputs, what)  # first: a link to an input is named as the input
    path = check_file_kind(path, what)
    if os.path.lexists(path) and not force:
        raise OutputExists(f"{what} {path} exists: qradar replaces no output unless told ({FORCE_HINT})")
    own_folder(path.parent, path)
    return path


def check_output_folder(folder: str | Path, names: Iterable[str], force: bool = False,
                        inputs: Iterable[str | Path | None] = ()) -> Path:
    """A folder of outputs: if it holds any of the files ``names`` the command writes, refused
    unless ``force`` (one of the command's ``inputs`` always, :func:`check_not_input`); then
    made if missing (:func:`own_folder`)."""
    folder = Path(folder)
    names, inputs = list(names), list(inputs)
    for n in names:
        check_not_input(folder / n, inputs)
    for n in names:
        check_file_kind(folder / n)
    if folder.is_dir():
        taken = [n for n in names if os.path.lexists(folder / n)]
        if taken and not force:
            raise OutputExists(f"{folder} holds {', '.join(taken)} already: qradar replaces no output unless told "
                               f"({FORCE_HINT}, or choose another --out)")
    return own_folder(folder)


@contextmanager
def output_folder(folder: str | Path, names: Iterable[str], force: bool = False,
                  inputs: Iterable[str | Path | None] = ()) -> Iterator[Path]:
    """:func:`check_output_folder`'s folder for the work of the ``with`` block: a folder it made
    is removed again when the work fails before writing into it (a wrong sensor, a recording
    without raw frames: no empty ``--out`` left behind); one holding a file stays."""
    existed = os.path.lexists(folder)
    made = check_output_folder(folder, names, force, inputs)
    try:
        yield made
    except BaseException:
        if not existed:
            try:
                made.rmdir()  # only when empty
            except OSError:
                pass
        raise


def pyplot():
    """matplotlib's pyplot on its file backend (Agg): the figures every command writes as
    PNG, on a host without a display."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
