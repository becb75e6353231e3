"""The code version recorded in every manifest."""

from importlib.metadata import PackageNotFoundError, version


def code_version() -> str:
    """The installed drivesim version, or `0+unknown` when run from a bare checkout."""
    try:
        return version("drivesim")
    except PackageNotFoundError:
        return "0+unknown"
