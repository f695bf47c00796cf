"""The package's version: its one home, on the lowest floor, so that the files every layer writes can name it."""

__version__ = "0.1.0"
