"""`yauyau serve` (not yet implemented)."""


def add_arguments(parser):
    pass


def run(args):
    raise SystemExit("yauyau serve: not implemented yet")
