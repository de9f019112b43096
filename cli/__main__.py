"""``python -m mapdb_cli``: the same as the ``mapdb`` command."""

from mapdb_cli.main import cli

cli()
