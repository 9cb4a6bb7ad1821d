from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Tensor(_message.Message):
    __slots__ = ("dtype", "shape", "data")
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    dtype: str
    shape: _containers.RepeatedScalarFieldContainer[int]
    data: bytes
    def __init__(self, dtype: _Optional[str] = ..., shape: _Optional[_Iterable[int]] = ..., data: _Optional[bytes] = ...) -> None: ...

class Image(_message.Message):
    __slots__ = ("png", "array")
    PNG_FIELD_NUMBER: _ClassVar[int]
    ARRAY_FIELD_NUMBER: _ClassVar[int]
    png: bytes
    array: Tensor
    def __init__(self, png: _Optional[bytes] = ..., array: _Optional[_Union[Tensor, _Mapping]] = ...) -> None: ...

class Frame(_message.Message):
    __slots__ = ("rgb", "depth", "pix_T_cam", "world_T_cam", "camera_id", "sequence", "timestamp", "scene_start", "capture_time")
    RGB_FIELD_NUMBER: _ClassVar[int]
    DEPTH_FIELD_NUMBER: _ClassVar[int]
    PIX_T_CAM_FIELD_NUMBER: _ClassVar[int]
    WORLD_T_CAM_FIELD_NUMBER: _ClassVar[int]
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_FIELD_NUMBER: _ClassVar[int]
    SCENE_START_FIELD_NUMBER: _ClassVar[int]
    CAPTURE_TIME_FIELD_NUMBER: _ClassVar[int]
    rgb: Image
    depth: Image
    pix_T_cam: Tensor
    world_T_cam: Tensor
    camera_id: str
    sequence: int
    timestamp: float
    scene_start: bool
    capture_time: float
    def __init__(self, rgb: _Optional[_Union[Image, _Mapping]] = ..., depth: _Optional[_Union[Image, _Mapping]] = ..., pix_T_cam: _Optional[_Union[Tensor, _Mapping]] = ..., world_T_cam: _Optional[_Union[Tensor, _Mapping]] = ..., camera_id: _Optional[str] = ..., sequence: _Optional[int] = ..., timestamp: _Optional[float] = ..., scene_start: _Optional[bool] = ..., capture_time: _Optional[float] = ...) -> None: ...

class Box3D(_message.Message):
    __slots__ = ("x", "y", "z", "lx", "ly", "lz", "yaw", "frame", "score", "label", "vx", "vy", "vz")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    LX_FIELD_NUMBER: _ClassVar[int]
    LY_FIELD_NUMBER: _ClassVar[int]
    LZ_FIELD_NUMBER: _ClassVar[int]
    YAW_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    LABEL_FIELD_NUMBER: _ClassVar[int]
    VX_FIELD_NUMBER: _ClassVar[int]
    VY_FIELD_NUMBER: _ClassVar[int]
    VZ_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    lx: float
    ly: float
    lz: float
    yaw: float
    frame: str
    score: float
    label: str
    vx: float
    vy: float
    vz: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ..., lx: _Optional[float] = ..., ly: _Optional[float] = ..., lz: _Optional[float] = ..., yaw: _Optional[float] = ..., frame: _Optional[str] = ..., score: _Optional[float] = ..., label: _Optional[str] = ..., vx: _Optional[float] = ..., vy: _Optional[float] = ..., vz: _Optional[float] = ...) -> None: ...

class Detections(_message.Message):
    __slots__ = ("boxes", "frame", "bundle_version", "camera_id", "sequence", "source_timestamp", "latency_s", "world_T_frame")
    BOXES_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    BUNDLE_VERSION_FIELD_NUMBER: _ClassVar[int]
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    SOURCE_TIMESTAMP_FIELD_NUMBER: _ClassVar[int]
    LATENCY_S_FIELD_NUMBER: _ClassVar[int]
    WORLD_T_FRAME_FIELD_NUMBER: _ClassVar[int]
    boxes: _containers.RepeatedCompositeFieldContainer[Box3D]
    frame: str
    bundle_version: str
    camera_id: str
    sequence: int
    source_timestamp: float
    latency_s: float
    world_T_frame: Tensor
    def __init__(self, boxes: _Optional[_Iterable[_Union[Box3D, _Mapping]]] = ..., frame: _Optional[str] = ..., bundle_version: _Optional[str] = ..., camera_id: _Optional[str] = ..., sequence: _Optional[int] = ..., source_timestamp: _Optional[float] = ..., latency_s: _Optional[float] = ..., world_T_frame: _Optional[_Union[Tensor, _Mapping]] = ...) -> None: ...
