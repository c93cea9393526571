"""`yauyau filter` (not yet implemented)."""


def add_arguments(parser):
    pass


def run(args):
    raise SystemExit("yauyau filter: not implemented yet")
