"""The conversions recon_node publishes with (frames, normal map, image and point-cloud
messages) give exactly what the message definitions and the formulas say.

The ``_reference_*`` functions below are those definitions written out as plainly as
possible, one step at a time: sensor_msgs/Image (rows of ``width * channels`` samples of
the encoding's type, little-endian, ``step`` bytes apart), sensor_msgs/PointCloud2 (one
record of float32 x, y, z, intensity at offsets 0, 4, 8, 12 per point, one row), the normal
map rgb = clip((n + 1) * 127.5) (zero outside the mask) and the optical <-> PS frame change
(y and z negated). Every message is compared with theirs field by field and as its CDR bytes
(what a subscriber receives), and decoded back to arrays compared exactly.
"""

from __future__ import annotations

import array as pyarray

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image, PointCloud2, PointField
from std_msgs.msg import Header

from fingerps_recon.photometric.frames import optical_to_ps, ps_to_optical
from fingerps_recon.photometric.normal_map import normal_map_rgb
from fingerps_ros.errors import MessageError
from fingerps_ros.image_conversion import array_to_image, image_to_array, images_to_array
from fingerps_ros.point_cloud_conversion import cloud_to_points, points_to_cloud

H, W = 37, 53  # odd sizes: rows of no power-of-two length

_ENCODINGS = {
    "mono8": (np.dtype(np.uint8), 1), "mono16": (np.dtype(np.uint16), 1),
    "rgb8": (np.dtype(np.uint8), 3), "bgr8": (np.dtype(np.uint8), 3),
    "32FC1": (np.dtype(np.float32), 1), "32FC3": (np.dtype(np.float32), 3),
}
_FLIP = np.array([1.0, -1.0, -1.0])
_FIELDS = ("x", "y", "z", "intensity")
_DTYPE = np.dtype([(name, "<f4") for name in _FIELDS])


# ------------------------------------------------------------------ the definitions
def _reference_array_to_image(array: np.ndarray, *, encoding: str,
                              header: Header | None = None) -> Image:
    dtype, channels = _ENCODINGS[encoding]
    data = np.ascontiguousarray(array, dtype=dtype.newbyteorder("<"))
    if data.ndim == 2:
        data = data[:, :, None]
    msg = Image()
    if header is not None:
        msg.header = header
    msg.height, msg.width = int(data.shape[0]), int(data.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = int(data.shape[1] * channels * dtype.itemsize)
    raw = pyarray.array("B")
    raw.frombytes(data.reshape(-1).view(np.uint8))
    msg.data = raw
    return msg


def _reference_image_to_array(msg: Image) -> np.ndarray:
    dtype, channels = _ENCODINGS[msg.encoding]
    dtype = dtype.newbyteorder(">" if msg.is_bigendian else "<")
    row_bytes = msg.width * channels * dtype.itemsize
    raw = np.frombuffer(bytes(msg.data), dtype=np.uint8, count=msg.step * msg.height)
    rows = raw.reshape(msg.height, msg.step)[:, :row_bytes]
    pixels = np.ascontiguousarray(rows).view(dtype).reshape(msg.height, msg.width, channels)
    pixels = pixels.astype(dtype.newbyteorder("="), copy=True)
    return pixels[:, :, 0] if channels == 1 else pixels


def _reference_points_to_cloud(points: np.ndarray, intensity: np.ndarray, *,
                               header: Header) -> PointCloud2:
    pts = np.asarray(points, dtype=np.float32)
    record = np.empty(pts.shape[0], dtype=_DTYPE)
    record["x"], record["y"], record["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    record["intensity"] = np.asarray(intensity, dtype=np.float32)
    fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
              for i, name in enumerate(_FIELDS)]
    return PointCloud2(
        header=header, height=1, width=int(pts.shape[0]), fields=fields, is_bigendian=False,
        point_step=_DTYPE.itemsize, row_step=_DTYPE.itemsize * int(pts.shape[0]),
        data=record.tobytes(), is_dense=True)


def _reference_normal_map_rgb(normals_ps: np.ndarray, *,
                              mask: np.ndarray | None = None) -> np.ndarray:
    n = np.asarray(normals_ps, dtype=np.float32)
    rgb = np.clip((n + 1.0) * 127.5, 0.0, 255.0).astype(np.uint8)
    if mask is not None:
        rgb[~np.asarray(mask, dtype=bool)] = 0
    return rgb


def _reference_flip(vectors: np.ndarray) -> np.ndarray:
    return np.asarray(vectors) * _FLIP


# ------------------------------------------------------------------ data
def _header() -> Header:
    return Header(stamp=Time(sec=1_700_000_123, nanosec=987_654_321),
                  frame_id="fingerps_camera_optical_frame")


def _normals(rng: np.random.Generator, dtype: type = np.float32) -> np.ndarray:
    """Unit normals (H, W, 3) with the awkward values a result may hold: NaN, +-0, +-inf,
    values just outside [-1, 1]."""
    n = rng.normal(size=(H, W, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n = n.astype(dtype)
    n[0, :6] = [[np.nan, 0.0, 1.0], [-0.0, -0.0, -1.0], [np.inf, -np.inf, 0.0],
                [1.0000001, -1.0000001, 2.0], [-3.0, 0.5, np.nan], [0.0, 0.0, 0.0]]
    return n


def _image(encoding: str, rng: np.random.Generator) -> np.ndarray:
    dtype, channels = _ENCODINGS[encoding]
    shape = (H, W) if channels == 1 else (H, W, channels)
    if dtype.kind == "u":
        return rng.integers(0, np.iinfo(dtype).max + 1, shape, dtype=dtype)
    array = rng.normal(size=shape).astype(np.float32)
    array.reshape(-1)[:4] = [np.nan, -0.0, np.inf, -np.inf]
    return array


def _assert_same_message(new: Image | PointCloud2, old: Image | PointCloud2) -> None:
    """Equal fields (the data bit for bit), and equal as a subscriber receives them.

    The CDR bytes themselves cannot be compared whole: rclpy leaves the alignment padding
    (e.g. after the frame_id string) uninitialised, so two serialisations of one message
    may differ there. They have the same length, decode to the same message and end with
    the same data bytes."""
    assert type(new) is type(old)
    assert new == old  # every field, the header and the data's bytes
    assert bytes(new.data) == bytes(old.data)
    wire_new, wire_old = serialize_message(new), serialize_message(old)
    assert len(wire_new) == len(wire_old)
    assert deserialize_message(wire_new, type(old)) == old
    tail = len(old.data) + (1 if isinstance(old, PointCloud2) else 0)  # + is_dense
    assert wire_new[len(wire_new) - tail:] == wire_old[len(wire_old) - tail:]


# ------------------------------------------------------------------ images
def _variants(array: np.ndarray) -> dict[str, np.ndarray]:
    """The array as the pipeline might hand it over: C order, Fortran order, a strided view
    of a larger array, float64."""
    wider = np.repeat(array, 2, axis=1)
    variants = {"c": array, "fortran": np.asfortranarray(array), "strided": wider[:, ::2]}
    if array.dtype.kind == "f":
        variants["float64"] = array.astype(np.float64) * (1.0 + 1e-9)  # rounds on the cast
    return variants


@pytest.mark.parametrize("encoding", sorted(_ENCODINGS))
def test_array_to_image_matches_the_reference(encoding: str) -> None:
    rng = np.random.default_rng(len(encoding))
    for name, array in _variants(_image(encoding, rng)).items():
        before = array.copy()
        new = array_to_image(array, encoding=encoding, header=_header())
        old = _reference_array_to_image(array, encoding=encoding, header=_header())
        _assert_same_message(new, old)
        assert (new.height, new.width, new.encoding, new.step, new.is_bigendian) == (
            old.height, old.width, encoding, old.step, 0), name
        np.testing.assert_array_equal(image_to_array(new), _reference_image_to_array(old))
        # The input is untouched, and the message owns its bytes.
        np.testing.assert_array_equal(array, before)
        array[...] = 0
        assert new == old, name


def test_array_to_image_without_header_and_with_int_input() -> None:
    array = np.arange(H * W, dtype=np.int64).reshape(H, W) * 7  # wraps around in mono8
    _assert_same_message(array_to_image(array, encoding="mono8"),
                         _reference_array_to_image(array, encoding="mono8"))
    _assert_same_message(array_to_image(array, encoding="mono16"),
                         _reference_array_to_image(array, encoding="mono16"))
    empty = np.zeros((0, W, 3), np.float32)
    _assert_same_message(array_to_image(empty, encoding="32FC3"),
                         _reference_array_to_image(empty, encoding="32FC3"))


def test_message_fields_stay_assignable() -> None:
    """The messages are made with check_fields=True: later assignments still work (and are
    checked)."""
    msg = array_to_image(np.zeros((2, 3), np.uint8), encoding="mono8")
    msg.data = bytes(range(6))
    assert isinstance(msg.data, pyarray.array) and list(msg.data) == list(range(6))
    np.testing.assert_array_equal(image_to_array(msg), np.arange(6).reshape(2, 3))
    with pytest.raises(AssertionError):
        msg.height = -1


def _padded(array: np.ndarray, encoding: str, *, pad: int, big_endian: bool) -> Image:
    dtype, channels = _ENCODINGS[encoding]
    dtype = dtype.newbyteorder(">" if big_endian else "<")
    row = W * channels * dtype.itemsize
    data = np.full((H, row + pad), 0xAB, dtype=np.uint8)
    data[:, :row] = np.ascontiguousarray(array, dtype=dtype).view(np.uint8).reshape(H, row)
    return Image(height=H, width=W, encoding=encoding, is_bigendian=int(big_endian),
                 step=row + pad, data=data.tobytes())


@pytest.mark.parametrize("encoding", sorted(_ENCODINGS))
@pytest.mark.parametrize(("pad", "big_endian"), [(0, False), (3, False), (5, True)])
def test_image_to_array_matches_the_reference(encoding: str, pad: int,
                                              big_endian: bool) -> None:
    array = _image(encoding, np.random.default_rng(7))
    msg = _padded(array, encoding, pad=pad, big_endian=big_endian)
    new, old = image_to_array(msg), _reference_image_to_array(msg)
    assert new.dtype == old.dtype and new.dtype.isnative and new.shape == old.shape
    assert new.flags.c_contiguous and new.flags.writeable
    assert new.tobytes() == old.tobytes()  # bit for bit, NaN payloads and -0.0 included
    assert not np.shares_memory(new, np.frombuffer(msg.data, np.uint8))


@pytest.mark.parametrize("encoding", ["mono8", "mono16", "32FC3"])
def test_images_to_array_is_the_stack_of_image_to_array(encoding: str) -> None:
    rng = np.random.default_rng(11)
    msgs = [array_to_image(_image(encoding, rng), encoding=encoding) for _ in range(3)]
    msgs.append(_padded(_image(encoding, rng), encoding, pad=3, big_endian=True))
    stack = images_to_array(msgs)
    expected = np.stack([_reference_image_to_array(m) for m in msgs])
    assert stack.dtype == expected.dtype and stack.shape == expected.shape
    assert stack.flags.c_contiguous and stack.tobytes() == expected.tobytes()
    stack[...] = 0  # a new array: the messages are untouched
    assert np.stack([image_to_array(m) for m in msgs]).tobytes() == expected.tobytes()


def test_images_to_array_refuses_what_cannot_be_stacked() -> None:
    small = array_to_image(np.zeros((2, 3), np.uint8), encoding="mono8")
    with pytest.raises(MessageError, match="at least one"):
        images_to_array([])
    with pytest.raises(MessageError, match="different encodings or sizes"):
        images_to_array([small, array_to_image(np.zeros((2, 4), np.uint8),
                                               encoding="mono8")])
    with pytest.raises(MessageError, match="different encodings or sizes"):
        images_to_array([small, array_to_image(np.zeros((2, 3), np.uint16),
                                               encoding="mono16")])
    short = Image(height=2, width=3, encoding="mono8", step=3, data=bytes(5))
    with pytest.raises(MessageError, match="too few"):
        images_to_array([small, short])


# ------------------------------------------------------------------ frames, normal map
@pytest.mark.parametrize("convert", [ps_to_optical, optical_to_ps])
def test_frame_flip_matches_the_reference(convert) -> None:
    rng = np.random.default_rng(3)
    n32 = _normals(rng)
    cases = {
        "image32": n32, "image64": n32.astype(np.float64), "rows": n32[3],
        "vector": n32[5, 5], "strided": n32[:, ::2], "fortran": np.asfortranarray(n32),
        "ints": np.arange(12).reshape(4, 3), "list": [[0.1, 0.2, 0.3]],
        "broadcast": np.array([[2.0], [3.0]]), "empty": np.zeros((0, 4, 3), np.float32),
    }
    for name, vectors in cases.items():
        new, old = convert(vectors), _reference_flip(vectors)
        assert new.dtype == old.dtype and new.shape == old.shape, name
        assert new.tobytes() == old.tobytes(), name
        as32 = convert(vectors, dtype=np.float32)
        assert as32.dtype == np.float32, name
        assert as32.tobytes() == old.astype(np.float32).tobytes(), name
    before = n32.copy()
    convert(n32, dtype=np.float32)[...] = 0  # a new array, the input untouched
    assert n32.tobytes() == before.tobytes()


def test_recon_nodes_normals_message_is_unchanged() -> None:
    """recon_node's normals: ps_to_optical(n, dtype=float32) in one pass instead of
    ps_to_optical(n).astype(float32)."""
    normals = _normals(np.random.default_rng(5))
    new = array_to_image(ps_to_optical(normals, dtype=np.float32), encoding="32FC3",
                         header=_header())
    old = _reference_array_to_image(_reference_flip(normals).astype(np.float32),
                                    encoding="32FC3", header=_header())
    _assert_same_message(new, old)


@pytest.mark.filterwarnings("ignore:invalid value encountered in cast")  # the NaN normals
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_normal_map_matches_the_reference(dtype: type) -> None:
    rng = np.random.default_rng(9)
    normals = _normals(rng, dtype)
    mask = rng.random((H, W)) < 0.6
    mask[0, :6] = True  # the awkward values are inside
    masks = {"none": None, "mask": mask, "all": np.ones((H, W), bool),
             "nothing": np.zeros((H, W), bool), "uint8": mask.astype(np.uint8),
             "per_channel": np.repeat(mask[..., None], 3, axis=2)}
    for name, m in masks.items():
        for layout, n in {"c": normals, "fortran": np.asfortranarray(normals),
                          "strided": np.repeat(normals, 2, axis=1)[:, ::2]}.items():
            before = n.copy()
            new = normal_map_rgb(n, mask=m)
            old = _reference_normal_map_rgb(n, mask=m)
            assert new.dtype == np.uint8 and new.shape == old.shape, (name, layout)
            assert new.tobytes() == np.ascontiguousarray(old).tobytes(), (name, layout)
            assert n.tobytes() == before.tobytes()
    shown = normal_map_rgb(normals, mask=mask)
    assert not shown[~mask].any() and shown[mask].any()
    _assert_same_message(array_to_image(shown, encoding="rgb8", header=_header()),
                         _reference_array_to_image(_reference_normal_map_rgb(
                             normals, mask=mask), encoding="rgb8", header=_header()))


# ------------------------------------------------------------------ point clouds
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_points_to_cloud_matches_the_reference(dtype: type) -> None:
    rng = np.random.default_rng(13)
    count = 1001
    points = (rng.normal(0.0, 0.01, (count, 3)) + np.array([0.0, 0.0, 0.09])).astype(dtype)
    points[:3] = [[np.nan, -0.0, np.inf], [0.0, 0.0, 0.0], [1e-40, -1e-40, 3.0e38]]
    intensity = rng.uniform(0.0, 1.0, count).astype(dtype)
    for layout, (p, i) in {
        "c": (points, intensity),
        "fortran": (np.asfortranarray(points), intensity),
        "strided": (np.repeat(points, 2, axis=0)[::2], np.repeat(intensity, 2)[::2]),
    }.items():
        new = points_to_cloud(p, i, header=_header())
        old = _reference_points_to_cloud(p, i, header=_header())
        _assert_same_message(new, old)
        assert (new.width, new.row_step, new.point_step) == (count, 16 * count, 16), layout
        new_points, new_intensity = cloud_to_points(new)
        record = np.frombuffer(bytes(old.data), dtype=_DTYPE)
        assert new_points.tobytes() == np.stack(
            [record["x"], record["y"], record["z"]], axis=1).astype(np.float32).tobytes()
        assert new_intensity.tobytes() == record["intensity"].tobytes()
        assert new_points.flags.writeable and new_points.dtype == np.float32
        assert not np.shares_memory(new_points, np.frombuffer(new.data, np.uint8))
    empty = points_to_cloud(np.zeros((0, 3)), np.zeros(0), header=_header())
    _assert_same_message(empty, _reference_points_to_cloud(np.zeros((0, 3)), np.zeros(0),
                                                           header=_header()))
