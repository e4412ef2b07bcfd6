"""The ``autocal`` command line: :mod:`.main` dispatches to one module per sub-command.

Each command module has ``add(subparsers)`` registering its parser and ``run(args)``
returning the exit status; shared argument parsing lives in :mod:`.args`.
"""
