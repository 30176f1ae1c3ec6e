"""Import the built-in representation kinds so that they register themselves."""

from . import neumip, parallax, pca, sh, triple_plane  # noqa: F401
