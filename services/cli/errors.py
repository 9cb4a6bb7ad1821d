"""The CLI's user-facing error type (its own module, so `python -m services.cli.main` and the
`n3dmap` console script see one and the same class)."""


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""
