"""The output checks every command makes before its work, declared once: the --force option and
one call that reports an output that cannot be written, or that would replace an input, as a
one-line error naming the path (rules: :mod:`humotion.io.paths`)."""

from __future__ import annotations

from pathlib import Path

import click

from humotion.io.errors import OutputPathError, base_suffix
from humotion.io.paths import check_output_file, check_output_folder, same_file

force_option = click.option("--force", is_flag=True,
                            help="Write an output even where it is one of the input files (replacing it).")


def check_outputs(files=(), folders=(), inputs=(), force: bool = False, formats: tuple[str, ...] | None = None,
                  written=()) -> None:
    """Before the work: each output file (None: not asked for) can be written (its folder exists
    and is writable) and, with formats, has one of those suffixes (a trailing .gz aside); each
    output folder exists writable or can be made; and, unless force, no output file, nor any of
    written (files the command makes inside its folders), is one of the inputs (None ignored),
    however spelled or linked. click.ClickException naming the path otherwise."""
    files = [Path(f) for f in files if f is not None]
    try:
        for path in files:
            check_output_file(path)
            suffix = base_suffix(path)
            if formats is not None and suffix not in formats:
                kind = f"cannot write {suffix!r} files" if suffix else "no suffix to say the format"
                raise OutputPathError(path, f"{kind}; writable: {', '.join(formats)}")
        for folder in folders:
            check_output_folder(folder)
    except OutputPathError as error:
        raise click.ClickException(str(error)) from None
    if force:
        return
    for path in files + [Path(f) for f in written]:
        for source in filter(None, inputs):
            if same_file(path, source):
                raise click.ClickException(f"{path} is the input file {source}: writing would replace it; "
                                           "give another output, or --force to replace it")
