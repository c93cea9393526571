"""`yauyau models` (not yet implemented)."""


def add_arguments(parser):
    pass


def run(args):
    raise SystemExit("yauyau models: not implemented yet")
