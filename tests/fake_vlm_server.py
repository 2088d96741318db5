"""A local stand-in for an OpenAI-compatible chat-completions server (tests of the VLM labeler).

``FakeVlmServer`` runs ``http.server.ThreadingHTTPServer`` on 127.0.0.1, port 0 (a free port), in
a daemon thread. Every request is recorded (path, headers, parsed JSON body). ``mode`` picks the
behaviour:

* ``"ok"``: answer ``responder(body) -> dict`` as JSON in ``choices[0].message.content``;
* ``"fenced"``: the same answer wrapped in prose and a ```json fence;
* ``"malformed"``: content that holds no JSON object;
* ``"schema"``: valid JSON that violates every prompt schema;
* ``"slow"``: sleep ``slow_seconds`` (past the client's timeout), then answer as ``"ok"``;
* ``"error_then_ok"``: HTTP ``error_status`` for the first ``errors_left`` requests, then ``"ok"``;
* ``"status"``: always HTTP ``error_status`` (e.g. 401), with a body that echoes the request's
  Authorization header, as careless servers do (the client must never repeat it);
* ``"garbage"``: HTTP 200 with a body that is not a chat-completions response;
* ``"redirect"``: HTTP 307 to the same path on this server (a client must not follow it).
"""
from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, Callable


class FakeVlmServer:
    def __init__(self, responder: Callable[[dict[str, Any]], dict[str, Any]] | None = None) -> None:
        self.responder = responder or (lambda body: {})
        self.mode = "ok"
        self.slow_seconds = 1.0
        self.error_status = 500
        self.errors_left = 0
        self.requests: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._httpd = ThreadingHTTPServer(("127.0.0.1", 0), _handler_for(self))
        self._httpd.daemon_threads = True
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.05},
                                        daemon=True)

    @property
    def base_url(self) -> str:
        host, port = self._httpd.server_address[:2]
        return f"http://{host}:{port}/v1"

    def start(self) -> "FakeVlmServer":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._httpd.shutdown()
        self._httpd.server_close()

    def reset(self, mode: str = "ok", **settings: Any) -> None:
        with self._lock:
            self.mode = mode
            self.requests.clear()
            for name, value in settings.items():
                setattr(self, name, value)

    # called from handler threads
    def _respond(self, handler: BaseHTTPRequestHandler, body: dict[str, Any] | None) -> tuple[int, bytes]:
        with self._lock:
            self.requests.append({"path": handler.path, "headers": dict(handler.headers.items()), "body": body})
            mode = self.mode
            if mode == "error_then_ok" and self.errors_left > 0:
                self.errors_left -= 1
                return self.error_status, b'{"error": {"message": "try again later"}}'
        if mode == "status":
            echo = handler.headers.get("Authorization", "")
            return self.error_status, json.dumps({"error": {"message": f"bad credentials: {echo}"}}).encode()
        if mode == "redirect":
            return 307, b""
        if mode == "garbage":
            return 200, b"<html>not json</html>"
        if mode == "slow":
            time.sleep(self.slow_seconds)
        if body is None:
            return 400, b'{"error": {"message": "body is not JSON"}}'
        if mode == "malformed":
            content = "Sure! The answer is: moving parts two, maybe {three"
        elif mode == "schema":
            content = json.dumps({"moving_parts": "two", "start": "all", "joints": 5})
        else:
            content = json.dumps(self.responder(body))
            if mode == "fenced":
                content = f"Here is the JSON you asked for:\n```json\n{content}\n```\nHope it helps."
        answer = {"id": "fake", "object": "chat.completion", "model": body.get("model"),
                  "choices": [{"index": 0, "finish_reason": "stop",
                               "message": {"role": "assistant", "content": content}}]}
        return 200, json.dumps(answer).encode()


def _handler_for(server: FakeVlmServer) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def do_POST(self) -> None:  # noqa: N802 - http.server naming
            length = int(self.headers.get("Content-Length") or 0)
            raw = self.rfile.read(length)
            try:
                body = json.loads(raw)
            except json.JSONDecodeError:
                body = None
            status, payload = server._respond(self, body)
            try:
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                if status == 307:
                    self.send_header("Location", server.base_url + "/chat/completions")
                self.send_header("Content-Length", str(len(payload)))
                self.end_headers()
                self.wfile.write(payload)
            except (BrokenPipeError, ConnectionResetError):
                pass  # the client timed out and left

        def log_message(self, *args: Any) -> None:
            pass

    return Handler
