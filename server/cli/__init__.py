"""The ``steelscan`` command line: :mod:`server.cli.main` builds the parser and runs a
sub-command; each module here is one group of sub-commands."""
