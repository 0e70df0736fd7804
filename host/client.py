"""A blocking client of the daemon's local API, used by the ``phantom`` CLI and by tests."""

from __future__ import annotations

import itertools
import json
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from phantom import PhantomError


class DaemonError(PhantomError):
    """The daemon answered a request with an error; ``code`` is one of the API's error codes."""

    def __init__(self, code: str, message: str):
        super().__init__(f"{message} [{code}]")
        self.code = code


class DaemonClient:
    """One connection to the daemon's Unix socket.

    Parameters
    ----------
    socket_path : path
        The daemon's socket.
    timeout_s : float
        How long (s) to wait for an answer before giving up.
    """

    def __init__(self, socket_path: str | Path, timeout_s: float = 120.0):
        self.socket_path = Path(socket_path)
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._socket.settimeout(timeout_s)
        try:
            self._socket.connect(str(self.socket_path))
        except (FileNotFoundError, ConnectionRefusedError) as error:
            self._socket.close()
            raise PhantomError(f"no daemon is listening on {self.socket_path}: start one with `phantom daemon` "
                               "(or pass the right --socket)") from error
        except PermissionError as error:
            self._socket.close()
            raise PhantomError(f"no permission to use {self.socket_path}: join the daemon's group") from error
        self._file = self._socket.makefile("rb")
        self._ids = itertools.count(1)

    def __enter__(self) -> DaemonClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the connection."""
        self._file.close()
        self._socket.close()

    def send_line(self, line: bytes) -> None:
        """Send raw bytes (tests use this to send malformed requests)."""
        self._socket.sendall(line)

    def read_message(self) -> dict[str, Any]:
        """The next JSON line from the daemon (a reply or an event)."""
        try:
            line = self._file.readline()
        except TimeoutError as error:
            raise PhantomError(f"the daemon on {self.socket_path} did not answer in time") from error
        if not line:
            raise PhantomError(f"the daemon on {self.socket_path} closed the connection")
        message: dict[str, Any] = json.loads(line)
        return message

    def call(self, method: str, params: dict[str, Any] | None = None) -> Any:
        """Send one request and return its result; raises DaemonError when it answers an error."""
        request_id = next(self._ids)
        self.send_line((json.dumps({"id": request_id, "method": method, "params": params or {}}) + "\n").encode())
        while True:
            message = self.read_message()
            if message.get("id") == request_id and "event" not in message:
                break
        if "error" in message:
            raise DaemonError(message["error"]["code"], message["error"]["message"])
        return message["result"]

    def events(self, topics: list[str] | None = None) -> Iterator[dict[str, Any]]:
        """Subscribe and yield ``{"event", "data"}`` messages as they come."""
        self.call("subscribe", {"topics": topics} if topics else {})
        while True:
            message = self.read_message()
            if "event" in message:
                yield message
