from n3dmap.v1 import types_pb2 as _types_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Stabilise(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    STABILISE_UNSPECIFIED: _ClassVar[Stabilise]
    STABILISE_EGOMOTION: _ClassVar[Stabilise]
    STABILISE_POSES: _ClassVar[Stabilise]
    STABILISE_NONE: _ClassVar[Stabilise]
STABILISE_UNSPECIFIED: Stabilise
STABILISE_EGOMOTION: Stabilise
STABILISE_POSES: Stabilise
STABILISE_NONE: Stabilise

class Grid(_message.Message):
    __slots__ = ("xmin", "xmax", "ymin", "ymax", "zmin", "zmax", "Z", "Y", "X")
    XMIN_FIELD_NUMBER: _ClassVar[int]
    XMAX_FIELD_NUMBER: _ClassVar[int]
    YMIN_FIELD_NUMBER: _ClassVar[int]
    YMAX_FIELD_NUMBER: _ClassVar[int]
    ZMIN_FIELD_NUMBER: _ClassVar[int]
    ZMAX_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    xmin: float
    xmax: float
    ymin: float
    ymax: float
    zmin: float
    zmax: float
    Z: int
    Y: int
    X: int
    def __init__(self, xmin: _Optional[float] = ..., xmax: _Optional[float] = ..., ymin: _Optional[float] = ..., ymax: _Optional[float] = ..., zmin: _Optional[float] = ..., zmax: _Optional[float] = ..., Z: _Optional[int] = ..., Y: _Optional[int] = ..., X: _Optional[int] = ...) -> None: ...

class ResponseInfo(_message.Message):
    __slots__ = ("bundle_version", "frame", "model_s", "queue_s", "batch_size")
    BUNDLE_VERSION_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    MODEL_S_FIELD_NUMBER: _ClassVar[int]
    QUEUE_S_FIELD_NUMBER: _ClassVar[int]
    BATCH_SIZE_FIELD_NUMBER: _ClassVar[int]
    bundle_version: str
    frame: str
    model_s: float
    queue_s: float
    batch_size: int
    def __init__(self, bundle_version: _Optional[str] = ..., frame: _Optional[str] = ..., model_s: _Optional[float] = ..., queue_s: _Optional[float] = ..., batch_size: _Optional[int] = ...) -> None: ...

class MapRequest(_message.Message):
    __slots__ = ("views", "features")
    VIEWS_FIELD_NUMBER: _ClassVar[int]
    FEATURES_FIELD_NUMBER: _ClassVar[int]
    views: _containers.RepeatedCompositeFieldContainer[_types_pb2.Frame]
    features: bool
    def __init__(self, views: _Optional[_Iterable[_Union[_types_pb2.Frame, _Mapping]]] = ..., features: _Optional[bool] = ...) -> None: ...

class MapResponse(_message.Message):
    __slots__ = ("info", "grid", "occupancy", "heightmap", "features", "observed")
    INFO_FIELD_NUMBER: _ClassVar[int]
    GRID_FIELD_NUMBER: _ClassVar[int]
    OCCUPANCY_FIELD_NUMBER: _ClassVar[int]
    HEIGHTMAP_FIELD_NUMBER: _ClassVar[int]
    FEATURES_FIELD_NUMBER: _ClassVar[int]
    OBSERVED_FIELD_NUMBER: _ClassVar[int]
    info: ResponseInfo
    grid: Grid
    occupancy: _types_pb2.Tensor
    heightmap: _types_pb2.Tensor
    features: _types_pb2.Tensor
    observed: _types_pb2.Tensor
    def __init__(self, info: _Optional[_Union[ResponseInfo, _Mapping]] = ..., grid: _Optional[_Union[Grid, _Mapping]] = ..., occupancy: _Optional[_Union[_types_pb2.Tensor, _Mapping]] = ..., heightmap: _Optional[_Union[_types_pb2.Tensor, _Mapping]] = ..., features: _Optional[_Union[_types_pb2.Tensor, _Mapping]] = ..., observed: _Optional[_Union[_types_pb2.Tensor, _Mapping]] = ...) -> None: ...

class PairRequest(_message.Message):
    __slots__ = ("views0", "views1")
    VIEWS0_FIELD_NUMBER: _ClassVar[int]
    VIEWS1_FIELD_NUMBER: _ClassVar[int]
    views0: _containers.RepeatedCompositeFieldContainer[_types_pb2.Frame]
    views1: _containers.RepeatedCompositeFieldContainer[_types_pb2.Frame]
    def __init__(self, views0: _Optional[_Iterable[_Union[_types_pb2.Frame, _Mapping]]] = ..., views1: _Optional[_Iterable[_Union[_types_pb2.Frame, _Mapping]]] = ...) -> None: ...

class FlowRequest(_message.Message):
    __slots__ = ("views0", "views1", "stabilise")
    VIEWS0_FIELD_NUMBER: _ClassVar[int]
    VIEWS1_FIELD_NUMBER: _ClassVar[int]
    STABILISE_FIELD_NUMBER: _ClassVar[int]
    views0: _containers.RepeatedCompositeFieldContainer[_types_pb2.Frame]
    views1: _containers.RepeatedCompositeFieldContainer[_types_pb2.Frame]
    stabilise: Stabilise
    def __init__(self, views0: _Optional[_Iterable[_Union[_types_pb2.Frame, _Mapping]]] = ..., views1: _Optional[_Iterable[_Union[_types_pb2.Frame, _Mapping]]] = ..., stabilise: _Optional[_Union[Stabilise, str]] = ...) -> None: ...

class EgomotionResponse(_message.Message):
    __slots__ = ("info", "cam0_T_cam1")
    INFO_FIELD_NUMBER: _ClassVar[int]
    CAM0_T_CAM1_FIELD_NUMBER: _ClassVar[int]
    info: ResponseInfo
    cam0_T_cam1: _types_pb2.Tensor
    def __init__(self, info: _Optional[_Union[ResponseInfo, _Mapping]] = ..., cam0_T_cam1: _Optional[_Union[_types_pb2.Tensor, _Mapping]] = ...) -> None: ...

class FlowResponse(_message.Message):
    __slots__ = ("info", "grid", "flow")
    INFO_FIELD_NUMBER: _ClassVar[int]
    GRID_FIELD_NUMBER: _ClassVar[int]
    FLOW_FIELD_NUMBER: _ClassVar[int]
    info: ResponseInfo
    grid: Grid
    flow: _types_pb2.Tensor
    def __init__(self, info: _Optional[_Union[ResponseInfo, _Mapping]] = ..., grid: _Optional[_Union[Grid, _Mapping]] = ..., flow: _Optional[_Union[_types_pb2.Tensor, _Mapping]] = ...) -> None: ...

class DetectRequest(_message.Message):
    __slots__ = ("views", "min_score")
    VIEWS_FIELD_NUMBER: _ClassVar[int]
    MIN_SCORE_FIELD_NUMBER: _ClassVar[int]
    views: _containers.RepeatedCompositeFieldContainer[_types_pb2.Frame]
    min_score: float
    def __init__(self, views: _Optional[_Iterable[_Union[_types_pb2.Frame, _Mapping]]] = ..., min_score: _Optional[float] = ...) -> None: ...

class MovingObjectsRequest(_message.Message):
    __slots__ = ("views0", "views1", "min_score")
    VIEWS0_FIELD_NUMBER: _ClassVar[int]
    VIEWS1_FIELD_NUMBER: _ClassVar[int]
    MIN_SCORE_FIELD_NUMBER: _ClassVar[int]
    views0: _containers.RepeatedCompositeFieldContainer[_types_pb2.Frame]
    views1: _containers.RepeatedCompositeFieldContainer[_types_pb2.Frame]
    min_score: float
    def __init__(self, views0: _Optional[_Iterable[_Union[_types_pb2.Frame, _Mapping]]] = ..., views1: _Optional[_Iterable[_Union[_types_pb2.Frame, _Mapping]]] = ..., min_score: _Optional[float] = ...) -> None: ...

class DetectionsResponse(_message.Message):
    __slots__ = ("info", "detections")
    INFO_FIELD_NUMBER: _ClassVar[int]
    DETECTIONS_FIELD_NUMBER: _ClassVar[int]
    info: ResponseInfo
    detections: _types_pb2.Detections
    def __init__(self, info: _Optional[_Union[ResponseInfo, _Mapping]] = ..., detections: _Optional[_Union[_types_pb2.Detections, _Mapping]] = ...) -> None: ...

class ModelsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ModelsResponse(_message.Message):
    __slots__ = ("bundle_version", "preset", "modules", "routes", "grid", "device", "meta_json")
    BUNDLE_VERSION_FIELD_NUMBER: _ClassVar[int]
    PRESET_FIELD_NUMBER: _ClassVar[int]
    MODULES_FIELD_NUMBER: _ClassVar[int]
    ROUTES_FIELD_NUMBER: _ClassVar[int]
    GRID_FIELD_NUMBER: _ClassVar[int]
    DEVICE_FIELD_NUMBER: _ClassVar[int]
    META_JSON_FIELD_NUMBER: _ClassVar[int]
    bundle_version: str
    preset: str
    modules: _containers.RepeatedScalarFieldContainer[str]
    routes: _containers.RepeatedScalarFieldContainer[str]
    grid: Grid
    device: str
    meta_json: str
    def __init__(self, bundle_version: _Optional[str] = ..., preset: _Optional[str] = ..., modules: _Optional[_Iterable[str]] = ..., routes: _Optional[_Iterable[str]] = ..., grid: _Optional[_Union[Grid, _Mapping]] = ..., device: _Optional[str] = ..., meta_json: _Optional[str] = ...) -> None: ...
