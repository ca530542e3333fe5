"""The arguments of ``hrn-pyg`` sub-commands, importable without torch.

``hrn_pyg.commands.<command>`` (a dash in the command's name becomes an underscore) holds
``add_arguments(parser)`` for a command and the constants its defaults are read from; the work,
``run(args)``, stays in the module :data:`hrn_pyg.cli.COMMANDS` names, imported only when the
command runs. So ``hrn-pyg <command> --help`` answers without loading torch. A command with no
module here defines its arguments in its own module.
"""
