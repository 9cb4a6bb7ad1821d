"""gRPC StreamMovingObjects options from call metadata: parsed values, refusals naming the key, round trip."""

import pytest

from services.inference.errors import InvalidInput
from services.inference.stream_options import stream_metadata, stream_options


def test_defaults_and_parsed_values():
    assert stream_options(None) == {"level": False}
    assert stream_options([("authorization", "Bearer x"), ("other", "1")]) == {"level": False}
    got = stream_options([("n3dmap-level", "TRUE"), ("n3dmap-level-ahead", "16"), ("n3dmap-ground-y", b"2.5")])
    assert got == {"level": True, "level_ahead": 16.0, "ground_y": 2.5}
    assert stream_options([("n3dmap-level", "0")]) == {"level": False}


@pytest.mark.parametrize("metadata, key", [
    ([("n3dmap-level", "yes")], "n3dmap-level"),
    ([("n3dmap-level", "1"), ("n3dmap-level-ahead", "far")], "n3dmap-level-ahead"),
    ([("n3dmap-level", "1"), ("n3dmap-level-ahead", "-1")], "n3dmap-level-ahead"),
    ([("n3dmap-level", "1"), ("n3dmap-ground-y", "nan")], "n3dmap-ground-y"),
    ([("n3dmap-level-ahead", "12")], "n3dmap-level-ahead"),          # placement without levelling
    ([("n3dmap-level", "false"), ("n3dmap-ground-y", "2")], "n3dmap-ground-y"),
    ([("n3dmap-level", "1"), ("n3dmap-level", "0")], "n3dmap-level"),  # twice
])
def test_refusals_name_the_key(metadata, key):
    with pytest.raises(InvalidInput) as e:
        stream_options(metadata)
    assert e.value.field == f"metadata {key}"


@pytest.mark.parametrize("options", [{}, {"level": True}, {"level": True, "level_ahead": 16.0, "ground_y": -0.5}])
def test_client_metadata_round_trips(options):
    assert stream_options(stream_metadata(**options)) == {"level": False, **options}
