"""The ``autocal`` command line: :mod:`.main` dispatches to one module per sub-command.

Each command module has ``add(subparsers)`` registering its parser and ``run(args)``
returning the exit status; shared argument parsing lives in :mod:`.args`. Command modules
import the science stack inside ``run`` so that parsing arguments and reporting a usage
error stay fast.
"""
