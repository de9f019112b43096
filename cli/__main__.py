"""``python -m mapdb_cli``: the same as the ``mapdb`` command."""

from .main import cli

cli()
