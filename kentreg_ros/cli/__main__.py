"""``kentreg replay|batch|register|convert|localize ...``: one command for the command lines.

``kentreg replay bags/balm_50`` runs exactly what ``kentreg_replay bags/balm_50`` runs (the same
``main``, with the rest of the arguments); the separate console scripts stay, since
``ros2 run kentreg_ros <script>`` needs them. Also ``python3 -m kentreg_ros.cli ...``.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

from kentreg_ros import __version__
from kentreg_ros.cli import common

PROG = 'kentreg'

#: Subcommand -> (module whose ``main`` runs it, one line of help).
COMMANDS = {
    'replay': ('kentreg_ros.cli.replay', 'offline odometry over a bag or a scan folder'),
    'batch': ('kentreg_ros.cli.batch', 'the replay over many recordings, on many cores'),
    'register': ('kentreg_ros.cli.register', 'register two scan files'),
    'convert': ('kentreg_ros.cli.convert', 'scan files (+ poses) or a bag to a rosbag2 MCAP'),
    'localize': ('kentreg_ros.cli.localize', 'localize the scans of a recording in a saved map'),
}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``kentreg``: dispatch to the subcommand's ``main``."""
    args = list(sys.argv[1:] if argv is None else argv)
    usage = '\n'.join(
        [f'usage: {PROG} {{{",".join(COMMANDS)}}} ...', '', 'commands:']
        + [f'  {name:<10} {text}' for name, (_, text) in COMMANDS.items()]
        + ['', f"'{PROG} COMMAND --help' describes a command."]
    )
    if not args:
        print(usage, file=sys.stderr)
        return common.EXIT_BAD_INPUT
    if args[0] in ('-h', '--help'):
        print(usage)
        return common.EXIT_OK
    if args[0] == '--version':
        print(f'{PROG} {__version__}')
        return common.EXIT_OK
    if args[0] not in COMMANDS:
        print(
            f'{PROG}: error: unknown command {args[0]!r}; expected one of {", ".join(COMMANDS)}',
            file=sys.stderr,
        )
        return common.EXIT_BAD_INPUT
    module = importlib.import_module(COMMANDS[args[0]][0])
    status: int = module.main(args[1:])
    return status


if __name__ == '__main__':
    sys.exit(main())
