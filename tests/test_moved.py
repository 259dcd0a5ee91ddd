"""Modules moved into subpackages keep their old names (indreg._moved): the same module object under both."""
import importlib

import pytest

from indreg._moved import MOVED


@pytest.mark.parametrize("old", sorted(MOVED))
def test_old_name_is_the_moved_module(old):
    assert importlib.import_module(old) is importlib.import_module(MOVED[old])


def test_old_from_imports_and_the_io_package_names():
    from indreg.conventions import CONVENTIONS
    from indreg.io import DataFileError, conventions, read_angles, read_image, write_image, write_volume  # noqa: F401
    from indreg.writers import write_image as same

    assert same is write_image and conventions.CONVENTIONS is CONVENTIONS
