"""Import the built-in representation kinds so that they register themselves."""
# Each built-in kind's module is imported here (triple_plane, neumip, pca, sh).
import importlib

for _name in ("triple_plane", "neumip", "pca", "sh"):
    try:
        importlib.import_module(f"{__package__}.{_name}")
    except ModuleNotFoundError as _e:  # a kind not written yet
        if _e.name != f"{__package__}.{_name}":
            raise
