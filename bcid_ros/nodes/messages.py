"""
The rclpy side of the nodes' messages: classes by type name, and building messages.

The names and the message type table are in :mod:`bcid_ros.identifier.interface`
(free of ROS); this module turns them into rclpy message classes and builds
the messages both nodes publish.
"""

from __future__ import annotations

import array
import importlib
from typing import Any, Sequence

import numpy as np
from rclpy.serialization import serialize_message
from std_msgs.msg import Bool, Float64MultiArray, MultiArrayDimension

from bcid_ros.identifier.interface import MESSAGE_TYPES
from bcid_ros.identifier.layouts import covariance_layout, estimate_layout, samples_layout


def message_class(ros_type: str) -> type:
    """Return the rclpy class of a full type name such as ``'std_msgs/msg/Float64'``."""
    package, kind, name = ros_type.split('/')
    return getattr(importlib.import_module(f'{package}.{kind}'), name)


def topic_class(type_name: str) -> type:
    """Return the rclpy class of an ``input_type``/``output_type`` value."""
    return message_class(MESSAGE_TYPES[type_name].ros_type)


def as_doubles(values: np.ndarray) -> array.array:
    """Return a float64 array as array('d'), which the message setter takes without a check."""
    result = array.array('d')
    result.frombytes(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    return result


def _dimensions(layout: Sequence[tuple[str, int, int]]) -> list[MultiArrayDimension]:
    return [MultiArrayDimension(label=label, size=size, stride=stride)
            for label, size, stride in layout]


def estimate_message(names: Sequence[str], values: Any = None) -> Float64MultiArray:
    """Return an estimate message whose layout carries the names (docs/nodes.md, Topics)."""
    message = Float64MultiArray()
    message.layout.dim = _dimensions([estimate_layout(names)])
    if values is not None:
        message.data = as_doubles(values)
    return message


def covariance_message(names: Sequence[str], values: Any = None) -> Float64MultiArray:
    """Return a ``~/parameter_covariance`` message: p x p, row-major, names on both axes."""
    message = Float64MultiArray()
    message.layout.dim = _dimensions(covariance_layout(names))
    if values is not None:
        message.data = as_doubles(np.asarray(values, dtype=float).reshape(-1))
    return message


def samples_message(rows: np.ndarray) -> Float64MultiArray:
    """Return a samples message of rows ``[y, u1, ..., ur]``: one sample, or a frame."""
    message = Float64MultiArray()
    message.layout.dim = _dimensions(samples_layout(rows.shape[0], rows.shape[1] - 1))
    message.data = as_doubles(rows.reshape(-1))
    return message


def valid_message(valid: bool) -> Bool:
    """Return the ``~/valid`` message."""
    return Bool(data=bool(valid))


class SerializedArray:
    """
    The CDR bytes of a Float64MultiArray whose layout stays the same, for ``Publisher.publish``.

    rclpy converts every field of a message into its C structure on each
    publish, about 10 µs for an estimate of six values on a 2-core machine,
    three times what publishing the serialised bytes costs. An estimate topic
    changes only its values, so rclpy serialises the message once per number
    of values, and the values' bytes are appended to that head afterwards.
    ``test/ros/test_nodes.py`` checks that rclpy reads the bytes back as the message.

    Parameters
    ----------
    message : std_msgs.msg.Float64MultiArray
        The message with its layout; its data are replaced.

    """

    def __init__(self, message: Float64MultiArray) -> None:
        self._message = message
        self._heads: dict[int, bytes] = {}

    def serialize(self, values: Any) -> bytes:
        """Return the serialised message with ``values`` (float64, flattened) as its data."""
        data = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
        head = self._heads.get(data.shape[0])
        if head is None:
            head = self._heads[data.shape[0]] = self._head(data.shape[0])
        return head + data.tobytes()

    def _head(self, count: int) -> bytes:
        """Serialise the message with ``count`` values and cut them off (they come last)."""
        marker = np.arange(1.0, count + 1.0)
        self._message.data = as_doubles(marker)
        whole = serialize_message(self._message)
        if not whole.endswith(marker.tobytes()):
            raise RuntimeError('the serialised Float64MultiArray does not end with its data')
        return whole[:len(whole) - marker.nbytes]


class SamplesLayouts:
    """The ``layout.dim`` of samples messages, built once per sample count."""

    def __init__(self, num_inputs: int) -> None:
        self.num_inputs = num_inputs
        self._layouts: dict[int, list[MultiArrayDimension]] = {}

    def message(self, data: np.ndarray, count: int) -> Float64MultiArray:
        """Return a samples message of ``count`` samples with the row-major ``data``."""
        layout = self._layouts.get(count)
        if layout is None:
            layout = self._layouts[count] = _dimensions(samples_layout(count, self.num_inputs))
        message = Float64MultiArray()
        message.layout.dim = layout
        message.data = as_doubles(data)
        return message


__all__ = ['SamplesLayouts', 'SerializedArray', 'as_doubles', 'covariance_message',
           'estimate_message', 'message_class', 'samples_message', 'topic_class',
           'valid_message']
