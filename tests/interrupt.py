"""An interrupted fit, for the resume tests: a callback that raises :class:`Stop` at a given step."""


class Stop(Exception):
    """Raised by :func:`stop_at`'s callback: the fit is interrupted (after its checkpoint)."""


def stop_at(step: int):
    """A :func:`dynbtf.training.fit` callback that interrupts the fit after global step ``step``."""
    def callback(info):
        if info["global_step"] == step:
            raise Stop
    return callback
