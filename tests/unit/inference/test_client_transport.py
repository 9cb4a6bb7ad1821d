"""RestClient's transport failures read as the gRPC client's: ServiceCallError "not_ready" when nothing listens,
"timeout" when the server does not answer in time; health() answers instead of raising."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from services.inference.client import Frames, RestClient, ServiceCallError


def _frames() -> Frames:
    K = np.array([[8, 0, 4, 0], [0, 8, 4, 0], [0, 0, 1, 0], [0, 0, 0, 1]], np.float32)
    return Frames(rgb=np.zeros((8, 8, 3), np.uint8), depth=np.ones((8, 8), np.float32), pix_T_cam=K)


def test_nothing_listening_is_not_ready_and_health_says_so():
    with socket.socket() as s:   # a port that was free a moment ago; nothing listens on it
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with RestClient(f"http://127.0.0.1:{port}", timeout_s=2.0) as client:
        with pytest.raises(ServiceCallError) as e:
            client.models()
        assert e.value.error == "not_ready" and "GET /v1/models: cannot reach the server" in e.value.detail
        with pytest.raises(ServiceCallError) as e:
            client.map(_frames())
        assert e.value.error == "not_ready"
        health = client.health()
        assert health["live"] is False and health["ready"] is False


def test_a_server_that_never_answers_is_a_timeout():
    with socket.socket() as listener:   # accepts connections (the kernel's backlog) but never replies
        listener.bind(("127.0.0.1", 0))
        listener.listen(4)
        with RestClient(f"http://127.0.0.1:{listener.getsockname()[1]}", timeout_s=0.3) as client:
            with pytest.raises(ServiceCallError) as e:
                client.models()
    assert e.value.error == "timeout" and "no answer within the client's timeout" in e.value.detail
