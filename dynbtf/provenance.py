"""Which BTF a model was fitted to: the source fingerprint and the check of a model against a BTF.

Every fitter records the BTF in the model file's provenance
(:func:`dynbtf.training.fit.training_provenance`): its name, size, direction sets
and :func:`source_fingerprint`. :func:`check_model_source` compares that record
with a BTF before a model is scored on it (``dynbtf eval``); ``dynbtf compare``
uses the same fingerprint for the models kept in its output directory.
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from .data.base import BTFSource
from .errors import InputError

__all__ = ["source_fingerprint", "check_model_source", "source_as_fitted", "DIRECTION_TOLERANCE"]

#: Largest difference of a direction's components (unit vectors) still counted as the same direction
#: (~0.006 degrees: directions survive format conversions, e.g. float32 storage, within it).
DIRECTION_TOLERANCE = 1e-4


def source_fingerprint(source: BTFSource, name: str | None = None) -> str:
    """SHA-256 of the BTF's name, shape and first and last images (pairs (0, 0) and the last, float32 bytes).

    Model files record the BTF's name and shape, not its content; a BTF that
    changed under the same name (a re-measured file, a revised simulator, another
    simulation seed) is caught by comparing this fingerprint with the recorded one.
    Reads two images.
    """
    digest = hashlib.sha256(repr((source.name if name is None else name, source.shape)).encode())
    for v, l in ((0, 0), (source.n_views - 1, source.n_lights - 1)):
        digest.update(np.ascontiguousarray(source.image(int(v), int(l)), dtype=np.float32).tobytes())
    return digest.hexdigest()


def _describe(record: dict[str, Any]) -> str:
    return (f"{record.get('name')!r} ({record.get('height')}x{record.get('width')} texels, "
            f"{record.get('n_views')} views x {record.get('n_lights')} lights)")


def _same_directions(recorded, actual: np.ndarray) -> bool:
    if recorded is None:  # older model files record only the counts
        return True
    try:
        recorded = np.asarray(recorded, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return recorded.shape == actual.shape and bool(np.all(np.abs(recorded - actual) <= DIRECTION_TOLERANCE))


def source_as_fitted(metadata: dict[str, Any], source: BTFSource) -> BTFSource:
    """``source`` as the model (its file's ``metadata``) saw it: resampled to the recorded size when the model was
    fitted to the BTF resampled (``dynbtf fit --texels``) and ``source`` has the size it had before; else
    ``source`` itself (:func:`check_model_source` then judges it)."""
    record = (metadata.get("provenance") or {}).get("source")
    before = record.get("resampled_from") if isinstance(record, dict) else None
    after = (record.get("height"), record.get("width")) if isinstance(record, dict) else None
    if (isinstance(before, list) and [source.height, source.width] == before and after != tuple(before)
            and all(isinstance(n, int) and not isinstance(n, bool) for n in after)):
        from .data.resampled import ResampledBTF

        return ResampledBTF(source, *after)  # an implausible size is an InputError naming height or width
    return source


def check_model_source(metadata: dict[str, Any], source: BTFSource, model: str = "the model") -> list[str]:
    """Check that ``source`` is the BTF the model (its file's ``metadata``) was fitted to.

    Raises
    ------
    InputError
        The BTF differs in size (texels, numbers of views or lights) or in its
        view or light directions, or it has another name and other values (another material);
        the message names both BTFs.

    Returns
    -------
    list of str
        Notes, for the caller to print: the BTF has another name but the same
        size, directions and values (a converted copy of the BTF the model was fitted
        to: another name with other values is an error); or it has the recorded name but other content (the recorded
        :func:`source_fingerprint` differs: the BTF changed since the fit, or it is a
        lossy copy such as a float16 ``.dbtf``, which keeps the name); or the model
        file records no source.
    """
    record = (metadata.get("provenance") or {}).get("source")
    if not isinstance(record, dict) or not record:
        return [f"{model} records no source BTF: not checked against {source.name!r}"]
    actual = {"name": source.name, "height": source.height, "width": source.width,
              "n_views": source.n_views, "n_lights": source.n_lights}
    fitted, given = _describe(record), _describe(actual)
    sizes = [k for k in ("height", "width", "n_views", "n_lights") if record.get(k) != actual[k]]
    if sizes:
        raise InputError(f"{model} was fitted to {fitted}, not to the BTF {given}: different size "
                         f"({', '.join(sizes)}); evaluate it on the BTF it was fitted to (--force to skip this check)")
    moved = [kind for kind, directions in (("view", source.views), ("light", source.lights))
             if not _same_directions(record.get(f"{kind}s"), np.asarray(directions, dtype=np.float64))]
    if moved:
        raise InputError(f"{model} was fitted to {fitted}, not to the BTF {given}: the {' and '.join(moved)} "
                         "directions differ; evaluate it on the BTF it was fitted to (--force to skip this check)")
    if record.get("name") != source.name:
        stored = record.get("fingerprint")
        if stored is not None and stored != source_fingerprint(source, name=record.get("name")):
            raise InputError(f"{model} was fitted to {fitted}, not to the BTF {given}: same size and directions "
                             "but other values (another material, or a lossy copy); evaluate it on the BTF it was "
                             "fitted to (--force to evaluate anyway)")
        return [f"{model} was fitted to {record.get('name')!r}, evaluated on {source.name!r} (same size, directions "
                "and values: a copy of that BTF)"] if stored is not None else \
            [f"{model} was fitted to {record.get('name')!r}, evaluated on {source.name!r} (same size and "
             "directions; the model file records no content fingerprint to compare)"]
    stored = record.get("fingerprint")
    if stored is not None:
        current = source_fingerprint(source)
        if stored != current:
            return [f"{model} was fitted to other content of {source.name!r} (fingerprint {str(stored)[:12]}, now "
                    f"{current[:12]}): the BTF changed since the fit, or it is a lossy copy (e.g. a float16 .dbtf)"]
    return []
