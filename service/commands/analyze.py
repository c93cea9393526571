"""`yauyau analyze` (not yet implemented)."""


def add_arguments(parser):
    pass


def run(args):
    raise SystemExit("yauyau analyze: not implemented yet")
