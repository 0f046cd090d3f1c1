r"""
Exponentially weighted lagged products of a stream of rows, added a block at a time.

The HAC covariance (:mod:`bcid_ros.estimators.hac`) keeps

.. math::

    S(k) = \sum_t w_t\, z_t z_{t-k}^T, \quad k = 0 \ldots L, \qquad
    w_t = \mu^{T - t},

of its scores :math:`z_t` (the newest row has weight 1). A row costs one
list append; every ``BLOCK`` rows the block is added, one matrix product per
lag: the block's rows times the same rows k earlier (a view of the block and
the L rows before it). One product of the rows with their windows
:math:`[z_t, \ldots, z_{t-L}]` is a little faster for one plant (42 against
55 us a block at p = 4, L = 17), but its windows are a copy L + 1 times the
block: for 100 plants 15 MB, 3.5 ms a block and 28 ms the first time (fresh
pages), against 1.2 ms (benchmarks/replay_stall.py ``--joints 100``).

K plants that do not step together (a batched estimator skips a plant whose
sample is missing or refused) keep a cursor each (:class:`PlantCursors`):
each plant's blocks, weights and counts are those of one plant fed that
plant's rows, and the plants whose blocks complete together are added in one
batched product. :class:`~bcid_ros.estimators.adequacy.AdequacyMonitor` uses
the same cursors.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: Rows kept in lists before they are added to the sums in one product (a block's
#: dozen numpy calls cost about as much as two hundred rows' list appends).
BLOCK = 256


def add_lagged_products(sums: np.ndarray, context: np.ndarray, rows: np.ndarray,
                        decay: float) -> np.ndarray:
    r"""
    Return the lagged product sums with a block of new rows added.

    Parameters
    ----------
    sums : numpy.ndarray, shape ``(..., d, d, L + 1)``
        :math:`S(k)_{ab} = \sum_t w_t z_{t,a} z_{t-k,b}` at ``[..., a, b, k]``.
    context : numpy.ndarray, shape ``(..., L, d)``
        The L rows before the block, oldest first (zeros before the start).
    rows : numpy.ndarray, shape ``(..., m, d)``
        The new rows, oldest first. Leading dimensions are plants.
    decay : float
        :math:`\mu`: the old sums are multiplied by :math:`\mu^m`, the rows by
        :math:`\mu^{\mathrm{age}}` (the newest by 1).

    Returns
    -------
    numpy.ndarray, shape ``(..., d, d, L + 1)``
        The new sums (a new array).

    """
    count = rows.shape[-2]
    lags = sums.shape[-1] - 1
    ring = np.concatenate((context, rows), axis=-2)
    if decay == 1.0:
        left = rows
    else:
        # w = mu^(age): the newest row has weight 1
        left = rows * (decay ** np.arange(count - 1, -1, -1, dtype=float))[:, None]
    left = np.swapaxes(left, -1, -2)
    sums = sums * decay ** count
    for k in range(lags + 1):  # ring[lags - k + t] = z_{t-k} of new row t
        sums[..., k] += left @ ring[..., lags - k:lags - k + count, :]
    return sums


def decayed_weights(weight: float, squared: float, count: int,
                    decay: float) -> tuple[float, float]:
    r"""
    Return :math:`\sum w` and :math:`\sum w^2` after ``count`` more rows with forgetting ``decay``.

    Each new row has weight 1 and multiplies the old weights by :math:`\mu`
    (their squares by :math:`\mu^2`).
    """
    if decay == 1.0:
        return weight + count, squared + count
    factor, factor2 = decay ** count, decay ** (2 * count)
    return (weight * factor + (1.0 - factor) / (1.0 - decay),
            squared * factor2 + (1.0 - factor2) / (1.0 - decay * decay))


def weights_of_counts(counts: Any, decay: float) -> tuple[Any, Any]:
    r"""
    Return :math:`\sum w` and :math:`\sum w^2` of ``counts`` rows (:func:`decayed_weights` from 0).

    ``counts`` is an int, or ``(K,)`` per plant: each plant's with the scalar
    arithmetic of one plant, bit for bit (one call per distinct count).
    """
    if np.ndim(counts) == 0:
        return decayed_weights(0.0, 0.0, counts, decay)
    weight, squared = np.empty(np.shape(counts)), np.empty(np.shape(counts))
    for count in np.unique(counts).tolist():
        plants = counts == count
        weight[plants], squared[plants] = decayed_weights(0.0, 0.0, count, decay)
    return weight, squared


def effective_size(weight: Any, squared: Any) -> Any:
    r"""
    Return the effective sample size :math:`(\sum w)^2 / \sum w^2` (0 without weights).

    Floats, or ``(K,)`` arrays: each plant's with the scalar arithmetic of one
    plant, bit for bit (a product and a quotient, each correctly rounded).
    """
    if np.ndim(weight) == 0:
        return weight * weight / squared if squared > 0.0 else 0.0
    positive = squared > 0.0
    return np.where(positive, weight * weight / np.where(positive, squared, 1.0), 0.0)


class PlantCursors:
    """
    The pending counts of K plants that fill blocks of rows, each at its own pace.

    A plant that records at a time moves its cursor by one; a plant whose count
    reaches ``block`` is full, and its count goes back to 0 (the owner adds its
    rows). The owner asks :meth:`place` where the rows of the plants that
    record go, writes them, then calls :meth:`advance`. Three cases, cheapest
    first: while all counts are equal (every plant has recorded every time)
    they are one shared count and the rows go to one position of every plant
    (a basic slice: one strided write, no array operation on the counts); when
    every plant records but the counts differ (since a plant missed a sample:
    they never meet again unless plants record apart), one fancy write and
    one increment; when only some plants record, their indices.

    Parameters
    ----------
    plants : int
        K.
    block : int
        The rows in a full block.

    """

    def __init__(self, plants: int, block: int) -> None:
        self.plants, self.block = plants, block
        self._counts = np.zeros(plants, dtype=np.intp)
        #: every plant, as indices (the rows of every plant when the counts differ)
        self.every = np.arange(plants)
        #: the count of every plant while they are all equal, else None
        self.shared: int | None = 0

    def place(self, rows: Any) -> tuple[Any, Any]:
        """
        Return where the next row of each plant in ``rows`` goes: (plants, positions).

        ``rows`` is a slice or indices. Every plant with a shared count: the
        slice and one int; else the plants as indices and their counts.
        """
        if isinstance(rows, slice) and rows == _ALL:
            if self.shared is not None:
                return _ALL, self.shared
            return self.every, self._counts
        rows = self.every[rows]
        return rows, self.counts()[rows]

    def advance(self, plants: Any) -> Any:
        """
        Move the cursors of ``plants`` (as :meth:`place` returned them) by one.

        Return the plants now full (their counts go back to 0): a slice,
        indices, or None if none is.
        """
        if plants is _ALL:  # every plant, one shared count
            shared = self.shared + 1
            self.shared = shared if shared < self.block else 0
            return None if shared < self.block else _ALL
        counts = self.counts()
        if plants is self.every:  # every plant, counts that differ and stay different
            counts += 1
            if counts.max() < self.block:
                return None
            full = np.flatnonzero(counts == self.block)
        else:
            counts[plants] += 1
            full = plants[counts[plants] == self.block]
        counts[full] = 0
        if plants is not self.every:
            self._share()
        return full if full.size else None

    def counts(self) -> np.ndarray:
        """Return the count of each plant (the array itself: change it through :meth:`set`)."""
        if self.shared is not None:
            self._counts[:] = self.shared
        return self._counts

    def set(self, rows: Any, count: Any) -> None:
        """Set the counts of ``rows``."""
        self.counts()[rows] = count
        self._share()

    def _share(self) -> None:
        """Keep the counts as one shared count if they are all equal."""
        counts = self._counts
        self.shared = int(counts[0]) if (counts == counts[0]).all() else None


class LaggedProducts:
    r"""
    The lagged product sums of :func:`add_lagged_products` fed one row at a time.

    One plant (``plants=None``) keeps its rows in a list (:meth:`append`: one
    list append per row) and adds them every ``BLOCK`` rows. K plants keep a
    cursor per plant (:class:`PlantCursors`, the pattern of
    :class:`~bcid_ros.estimators.bcrls.LaggedMoments`): a buffer of ``BLOCK``
    rows per plant, so that a plant that does not record at some time (a
    missing or refused sample) keeps its own blocks, weights and count.
    :meth:`record` writes the rows of the plants that record now; the plants
    whose buffer is full are added in one batched call (in the common case,
    all plants at once). Plant k's sums are those of one plant fed plant k's
    rows: the weights bit for bit, the sums within rounding.

    Parameters
    ----------
    width : int
        d, the length of a row.
    lags : int
        L, the largest lag kept.
    decay : float
        :math:`\mu` in (0, 1].
    plants : int, optional
        K: rows are ``(K, d)``; the sums, weights and counts have a leading
        plant axis. None: rows are ``(d,)`` (one plant); the weights and the
        count are scalars.

    """

    def __init__(self, *, width: int, lags: int, decay: float, plants: int | None = None) -> None:
        self.width = width
        self.lags = lags
        self.decay = decay
        self.plants = plants
        self._lead = () if plants is None else (plants,)
        self.reset()

    def reset(self) -> None:
        """Forget every row (of every plant)."""
        self.sums = np.zeros(self._lead + (self.width, self.width, self.lags + 1))
        self.context = np.zeros(self._lead + (self.lags, self.width))
        if self.plants is None:
            #: the rows not yet added (one plant)
            self.pending: list[Any] = []
            # the factor of each pending row (1.0 from append): the products are formed
            # for a block at once (append_product)
            self.factors: list[float] = []
            #: sum of the weights and of their squares over the rows in the sums
            self.weight: Any = 0.0
            self.squared_weight: Any = 0.0
            #: rows in the sums
            self.count: Any = 0
            return
        #: the rows not yet added, per plant, ``cursors`` of them
        self.buffer = np.zeros((self.plants, BLOCK, self.width))
        self.cursors = PlantCursors(self.plants, BLOCK)
        self.weight = np.zeros(self.plants)
        self.squared_weight = np.zeros(self.plants)
        self.count = np.zeros(self.plants, dtype=np.int64)

    def clear(self, rows: Any) -> None:
        """Forget the rows of the plants ``rows`` (indices or a slice; one plant: all)."""
        if self.plants is None:
            self.reset()
            return
        for array in (self.sums, self.context, self.buffer, self.weight, self.squared_weight,
                      self.count):
            array[rows] = 0
        self.cursors.set(rows, 0)

    # ------------------------------------------------------------ the stream
    def append(self, row: Any) -> bool:
        """
        Keep one row of every plant, ``(d,)`` or ``(K, d)``; return whether a block was added.

        One plant keeps ``row`` by reference (do not change it); K plants copy
        it (:meth:`record` of every plant).
        """
        if self.plants is not None:
            return self.record(_ALL, row) > 0
        return self.append_product(row, 1.0)

    def append_product(self, row: Any, factor: float) -> bool:
        """
        Keep ``row`` times ``factor`` (one plant), the product formed with the block's.

        ``row`` is kept by reference (do not change it); return whether a block was added.
        """
        self.factors.append(factor)
        pending = self.pending
        pending.append(row)
        if len(pending) < BLOCK:
            return False
        self.flush()
        return True

    def extend(self, rows: Any) -> None:
        """
        Keep the rows ``(m, d)`` of one plant, oldest first (copied): :meth:`append` of each.

        The same sums, bit for bit: the rows that complete the pending block are
        appended, each whole block after them is added as :meth:`flush` adds it
        (without a list of its rows), the rest appended.
        """
        if self.plants is not None:
            raise ValueError('extend keeps the rows of one plant; K plants record with record()')
        rows = np.array(rows, dtype=float, ndmin=2)
        first = min(rows.shape[0], -len(self.pending) % BLOCK)
        for row in rows[:first]:
            self.append_product(row, 1.0)
        end = first + (rows.shape[0] - first) // BLOCK * BLOCK
        for start in range(first, end, BLOCK):
            self.add(rows[start:start + BLOCK])
        for row in rows[end:]:
            self.append_product(row, 1.0)

    def record(self, rows: Any, values: Any) -> int:
        """
        Keep one row of each plant in ``rows`` (K plants); add the buffers that are full.

        Parameters
        ----------
        rows : numpy.ndarray or slice
            The plants that record now: distinct indices, or a slice.
        values : numpy.ndarray, shape ``(R, d)``
            Their rows, in the order of ``rows`` (copied).

        Returns
        -------
        int
            How many plants' buffers were added to the sums.

        Raises
        ------
        ValueError
            If the sums are of one plant (``plants=None``).

        """
        if self.plants is None:
            raise ValueError('record needs plants=K; one plant keeps its rows with append()')
        plants, positions = self.cursors.place(rows)
        self.buffer[plants, positions] = values
        full = self.cursors.advance(plants)
        if full is None:
            return 0
        self._add(full, self.buffer[full])
        return self.plants if isinstance(full, slice) else full.size

    def flush(self) -> None:
        """Add the pending rows (of every plant) to the sums."""
        if self.plants is None:
            if not self.pending:
                return
            rows = self._pending_rows()
            self.pending, self.factors = [], []
            self.add(rows)
            return
        counts = self.cursors.counts()
        for count in np.unique(counts[counts > 0]).tolist():
            plants = np.flatnonzero(counts == count)
            self._add(plants, self.buffer[plants, :count])
        self.cursors.set(_ALL, 0)

    def add(self, rows: np.ndarray) -> None:
        """
        Add a block of rows, ``(m, d)`` or ``(m, K, d)``, oldest first, to the sums.

        Every plant takes m rows. Non-finite rows count as zero rows (their
        weight still counts).
        """
        self._add(_ALL, rows if self.plants is None else np.swapaxes(rows, 0, 1))

    def _add(self, plants: Any, rows: np.ndarray) -> None:
        """Add ``rows``, ``(m, d)`` or ``(R, m, d)`` of the plants ``plants``, to the sums."""
        finite = np.isfinite(rows).all(axis=-1)
        if not finite.all():
            rows = np.where(finite[..., None], rows, 0.0)
        context = self.context[plants]
        self.sums[plants] = add_lagged_products(self.sums[plants], context, rows, self.decay)
        ring = np.concatenate((context, rows), axis=-2)
        self.context[plants] = ring[..., ring.shape[-2] - self.lags:, :]
        count = rows.shape[-2]
        if self.plants is None:
            self.weight, self.squared_weight = decayed_weights(
                self.weight, self.squared_weight, count, self.decay)
            self.count += count
            return
        # element-wise with one plant's scalar factors: the weights of one plant, bit for bit
        self.weight[plants], self.squared_weight[plants] = decayed_weights(
            self.weight[plants], self.squared_weight[plants], count, self.decay)
        self.count[plants] += count

    # ------------------------------------------------------------ the results
    def lag(self, k: int) -> np.ndarray:
        """Return S(k), shape ``(..., d, d)``, of the rows added so far."""
        return self.sums[..., k]

    @property
    def samples(self) -> Any:
        """Count the rows recorded, added or pending: an int, or ``(K,)``."""
        if self.plants is None:
            return self.count + len(self.pending)
        return self.count + self.cursors.counts()

    # ------------------------------------------------------------ the state
    def _pending_rows(self) -> np.ndarray:
        """Return the pending rows of one plant times their factors, ``(m, d)``."""
        rows = np.array(self.pending, dtype=float).reshape((len(self.pending), self.width))
        return rows * np.array(self.factors)[:, None]

    def state(self) -> dict[str, Any]:
        """Return copies of everything that defines the sums and the pending rows."""
        if self.plants is None:
            pending = self._pending_rows()
            return {'sums': self.sums.copy(), 'context': self.context.copy(),
                    'pending': pending, 'weight': self.weight,
                    'squared_weight': self.squared_weight, 'count': self.count}
        return {'sums': self.sums.copy(), 'context': self.context.copy(),
                'buffer': self.buffer.copy(), 'pending': self.cursors.counts().copy(),
                'weight': self.weight.copy(), 'squared_weight': self.squared_weight.copy(),
                'count': self.count.copy()}

    def load(self, state: dict[str, Any]) -> None:
        """Continue from a :meth:`state` of sums with the same settings."""
        self.sums = np.array(state['sums'], dtype=float)
        self.context = np.array(state['context'], dtype=float)
        if self.plants is None:
            self.pending = list(np.array(state['pending'], dtype=float))
            self.factors = [1.0] * len(self.pending)
            self.weight = float(state['weight'])
            self.squared_weight = float(state['squared_weight'])
            self.count = int(state['count'])
            return
        if 'buffer' in state:
            self.buffer = np.array(state['buffer'], dtype=float)
            self.cursors.set(_ALL, np.asarray(state['pending'], dtype=np.intp))
        else:  # the pending rows (m, K, d) that all plants shared before the cursors
            rows = np.array(state['pending'], dtype=float)
            self.buffer[:] = 0.0
            self.buffer[:, :rows.shape[0]] = np.swapaxes(rows, 0, 1)
            self.cursors.set(_ALL, rows.shape[0])
        lead = (self.plants,)
        self.weight = np.broadcast_to(np.asarray(state['weight'], dtype=float), lead).copy()
        self.squared_weight = np.broadcast_to(
            np.asarray(state['squared_weight'], dtype=float), lead).copy()
        self.count = np.broadcast_to(np.asarray(state['count'], dtype=np.int64), lead).copy()

    def plant_state(self, plant: int) -> dict[str, Any]:
        """Return plant k's sums and pending rows as one plant's :meth:`state` (K plants)."""
        count = int(self.cursors.counts()[plant])
        return {'sums': self.sums[plant].copy(), 'context': self.context[plant].copy(),
                'pending': self.buffer[plant, :count].copy(),
                'weight': float(self.weight[plant]),
                'squared_weight': float(self.squared_weight[plant]),
                'count': int(self.count[plant])}

    def load_plant(self, plant: int, state: dict[str, Any]) -> None:
        """Take over plant k's sums and pending rows from one plant's :meth:`state`."""
        rows = np.array(state['pending'], dtype=float).reshape(-1, self.width)
        self.sums[plant] = state['sums']
        self.context[plant] = state['context']
        self.buffer[plant] = 0.0
        self.buffer[plant, :rows.shape[0]] = rows
        self.cursors.set(plant, rows.shape[0])
        self.weight[plant] = float(state['weight'])
        self.squared_weight[plant] = float(state['squared_weight'])
        self.count[plant] = int(state['count'])


#: Every plant, as rows (a slice: views, not copies).
_ALL = slice(None)
