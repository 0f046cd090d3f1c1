"""The way in of a fake estimator that records what the feeders give it (no estimation)."""

from bcid_ros.estimators.blocks import BlockStopped


class BlockRecorder:
    """
    ``update_block`` as an estimator's: logs each row's y, stops at a y in ``fail_on``.

    A feeder test's fake estimator takes this and keeps ``log`` (a list) and
    ``fail_on`` (a set of outputs whose update raises FloatingPointError).
    """

    def update_block(self, rows, times=None):
        """Record an update per row (or stop at a chosen y, as the estimators do)."""
        for taken, y in enumerate(rows[:, 0].tolist()):
            if y in self.fail_on:
                if times is not None:
                    times.add(taken)
                raise BlockStopped(taken, FloatingPointError('boom'))
            self.log.append(y)
        if times is not None:
            times.add(len(rows))
        return len(rows)
