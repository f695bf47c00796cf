"""Command-line entry points of the library (``python -m anm_torchrl.cli.<name> --help``): the top floor, importing
the library and imported by nothing in it. Hydra recipes live in ``recipes/``."""
