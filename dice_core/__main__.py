"""``python -m dice_core check PATH/dataset.yaml [--data]``: check a dataset before reducing it
(:mod:`dice_core.check`)."""

import sys

COMMANDS = {"check": "check a dataset: its manifest, every file's header (--data: every sample and checksum), "
                     "what the workflow would reduce and skip, every problem"}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] not in COMMANDS:
        listed = "\n".join(f"  {name}: {text}" for name, text in COMMANDS.items())
        print(f"usage: python -m dice_core COMMAND ...\ncommands:\n{listed}", file=sys.stderr)
        return 2
    from dice_core import check

    return check.main(argv[1:])


if __name__ == "__main__":
    raise SystemExit(main())
