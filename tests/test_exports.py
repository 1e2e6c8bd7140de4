"""The public API is exactly what ``srvwire.__all__`` lists, sorted, and every name resolves."""

import srvwire


def test_all_is_sorted_and_unique() -> None:
    names = [name for name in srvwire.__all__ if name != "__version__"]
    assert names == sorted(names)
    assert len(set(srvwire.__all__)) == len(srvwire.__all__)


def test_every_exported_name_exists() -> None:
    for name in srvwire.__all__:
        assert hasattr(srvwire, name), name


def test_public_names_are_all_exported() -> None:
    public = {
        name
        for name, value in vars(srvwire).items()
        if not name.startswith("_") and getattr(value, "__module__", "").startswith("srvwire.")
    }
    assert public <= set(srvwire.__all__)
