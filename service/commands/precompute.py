"""`yauyau precompute` (not yet implemented)."""


def add_arguments(parser):
    pass


def run(args):
    raise SystemExit("yauyau precompute: not implemented yet")
