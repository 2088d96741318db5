"""OpenAI-compatible chat-completions client (stdlib ``urllib`` only) and JSON answer checking.

:class:`VlmClient` POSTs ``{base_url}/chat/completions`` with one user message made of a text part
and ``image_url`` parts (PNG data URLs), ``temperature`` 0 and ``response_format`` ``json_object``.
It works with hosted services (Bearer key) and local servers (no key: no ``Authorization`` header).
Timeouts, connection errors, HTTP 429 and 5xx are retried with exponential backoff; any other
4xx is not, and redirects are not followed.

Limits (a misbehaving server cannot hang or exhaust the process): every attempt has ONE total
deadline of ``timeout`` seconds covering connect, TLS, headers and body (a watchdog shuts the
socket down when it passes, so a server dripping a byte a second cannot extend it); a response
body over ``MAX_BODY_BYTES`` is refused; JSON (the response and the answer inside it) nested more
than ``MAX_JSON_DEPTH`` levels, ``NaN``/``Infinity`` literals and numbers too large for a float are
refused; a bool is never a number. :func:`extract_json` pulls the JSON object out of an
answer (bare, in a ```json fence, or after prose); :func:`validate_json` checks it against the
subset of JSON Schema the prompt schemas use.

Secrets: the API key lives only in the request header. It is never part of ``repr``, an exception,
a warning or a log line; every message built from server-controlled text goes through
:meth:`VlmClient.redact` first, and response bodies of 401/403 are never quoted.
"""
from __future__ import annotations

import http.client
import json
import math
import os
import re
import socket
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from typing import Any, Callable, Sequence

ENV_BASE_URL = ("SPARSEART_VLM_BASE_URL", "OPENAI_BASE_URL")
ENV_MODEL = "SPARSEART_VLM_MODEL"
ENV_KEY = "SPARSEART_VLM_API_KEY"
ENV_OPENAI_KEY = "OPENAI_API_KEY"
LOCAL_HOSTS = ("localhost", "127.0.0.1", "::1")
MAX_ANSWER_CHARS = 200_000
MAX_BODY_BYTES = 4 * 2**20      # a chat-completions response with a JSON answer is a few KiB
MAX_JSON_DEPTH = 32             # the deepest expected document (response + answer) has 5 levels
SNIPPET_CHARS = 160


class VlmError(RuntimeError):
    """A VLM request or answer failed. ``str(error)`` is one line and never holds the API key."""


class VlmServiceError(VlmError):
    """The service failed (no server, timeout, HTTP error) after the allowed retries."""


class VlmAnswerError(VlmError):
    """The service answered, but not with a usable JSON object (not JSON, wrong schema)."""


class VlmClient:
    """Chat-completions client.

    Args:
        base_url: e.g. ``http://127.0.0.1:8000/v1``; default ``$SPARSEART_VLM_BASE_URL`` then
            ``$OPENAI_BASE_URL``. ``/chat/completions`` is appended.
        model: model name sent in every request; default ``$SPARSEART_VLM_MODEL``.
        api_key: Bearer key; default ``$SPARSEART_VLM_API_KEY``, else ``$OPENAI_API_KEY`` but only
            when the base URL itself came from ``$OPENAI_BASE_URL`` or points at api.openai.com (an
            OpenAI key is not sent to some other server). None or "" = no Authorization header.
        timeout: seconds per attempt, in total (connect + TLS + headers + body), enforced by a
            watchdog rather than per socket read.
        max_retries: extra attempts after a timeout, connection error, 429 or 5xx.
        backoff: seconds before the first retry, doubled each retry, capped at ``max_backoff``
            (a 429's numeric Retry-After is honoured up to ``max_backoff``).
        sleep: injectable sleep (tests).

    Raises:
        ValueError: no base URL or model, a URL that is not http(s), or a bad number.
    """

    def __init__(self, base_url: str | None = None, model: str | None = None, api_key: str | None = None,
                 timeout: float = 30.0, max_retries: int = 2, backoff: float = 0.5, max_backoff: float = 8.0,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        url_source = "option"
        if not base_url:
            for name in ENV_BASE_URL:
                if os.environ.get(name):
                    base_url, url_source = os.environ[name], name
                    break
        if not base_url:
            raise ValueError("VLM labeler: no base URL: pass base_url (--vlm-base-url) or set "
                             "SPARSEART_VLM_BASE_URL")
        parsed = urllib.parse.urlsplit(base_url)
        if parsed.scheme not in ("http", "https") or not parsed.hostname:
            raise ValueError(f"VLM labeler: base URL must be http(s)://host[:port][/path], got {base_url!r}")
        model = model or os.environ.get(ENV_MODEL)
        if not model:
            raise ValueError("VLM labeler: no model name: pass model (--vlm-model) or set SPARSEART_VLM_MODEL")
        if not (timeout > 0 and max_retries >= 0 and backoff >= 0 and max_backoff >= 0):
            raise ValueError("VLM labeler: timeout must be > 0 and max_retries, backoff, max_backoff >= 0")
        if api_key is None:
            api_key = os.environ.get(ENV_KEY) or None
            openai_host = parsed.hostname == "api.openai.com"
            if api_key is None and (url_source == "OPENAI_BASE_URL" or openai_host):
                api_key = os.environ.get(ENV_OPENAI_KEY) or None
        self.base_url = base_url.rstrip("/")
        self.endpoint = self.base_url + "/chat/completions"
        self.model = str(model)
        self.timeout = float(timeout)
        self.max_retries = int(max_retries)
        self.backoff = float(backoff)
        self.max_backoff = float(max_backoff)
        self._sleep = sleep
        self._api_key = api_key or None
        local = parsed.hostname in LOCAL_HOSTS
        handlers: list[urllib.request.BaseHandler] = [_NoRedirect()]  # a redirect would carry the key elsewhere
        if local:
            handlers.append(urllib.request.ProxyHandler({}))  # never proxy a local server
        self._handlers = handlers

    def __repr__(self) -> str:
        return (f"VlmClient(endpoint={self.endpoint!r}, model={self.model!r}, "
                f"api_key={'set' if self._api_key else 'none'}, timeout={self.timeout})")

    @property
    def has_key(self) -> bool:
        return self._api_key is not None

    def redact(self, text: str) -> str:
        """``text`` with the API key (and its leading 8 / trailing 4 characters, which services
        echo in error messages) replaced by ``***``."""
        key = self._api_key
        if not key:
            return text
        text = text.replace(key, "***")
        if len(key) >= 12:
            text = text.replace(key[:8], "***").replace(key[-4:], "***")
        return text

    # ------------------------------------------------------------------ requests

    def request_body(self, text: str, image_urls: Sequence[str]) -> dict[str, Any]:
        """The JSON body of one request: a user message with a text part and image parts."""
        content: list[dict[str, Any]] = [{"type": "text", "text": text}]
        content += [{"type": "image_url", "image_url": {"url": url}} for url in image_urls]
        return {"model": self.model, "messages": [{"role": "user", "content": content}],
                "temperature": 0, "response_format": {"type": "json_object"}}

    def complete(self, text: str, image_urls: Sequence[str] = ()) -> str:
        """Send one request and return the answer text (``choices[0].message.content``).

        Raises:
            VlmServiceError: no server, timeout, HTTP error (after retries where allowed).
            VlmAnswerError: HTTP 200 with a body that is not a chat-completions response.
        """
        payload = json.dumps(self.request_body(text, image_urls)).encode()
        headers = {"Content-Type": "application/json", "Accept": "application/json",
                   "User-Agent": "sparseart-vlm/1"}
        if self._api_key:
            headers["Authorization"] = f"Bearer {self._api_key}"
        attempt = 0
        while True:
            request = urllib.request.Request(self.endpoint, data=payload, headers=headers, method="POST")
            deadline = _Deadline(self.timeout)
            try:
                try:
                    with self._open(request, deadline) as response:
                        body = _read_capped(response, deadline)
                finally:
                    deadline.cancel()
                return self._content(body)
            except urllib.error.HTTPError as error:
                code = int(error.code)
                retry_after = _retry_after(error.headers.get("Retry-After") if error.headers else None)
                cause = self._http_cause(error)
                error.close()
                if not (code == 429 or code >= 500) or attempt >= self.max_retries:
                    raise VlmServiceError(self._tried(cause, attempt)) from None
            except _BodyTooLarge as error:
                raise VlmServiceError(self._tried(str(error), attempt)) from None
            except (urllib.error.URLError, TimeoutError, socket.timeout, ConnectionError,
                    http.client.HTTPException, OSError, ValueError) as error:
                retry_after = None
                cause = (f"timed out (no complete answer within {self.timeout:g} s)" if deadline.fired
                         else self._network_cause(error))
                if attempt >= self.max_retries:
                    raise VlmServiceError(self._tried(cause, attempt)) from None
            delay = min(self.max_backoff, self.backoff * 2 ** attempt)
            if retry_after is not None:
                delay = min(self.max_backoff, max(delay, retry_after))
            self._sleep(delay)
            attempt += 1

    def _open(self, request: urllib.request.Request, deadline: "_Deadline"):
        """Open ``request`` with this client's handlers plus ones that put every socket of the
        attempt under ``deadline``."""
        opener = urllib.request.build_opener(*self._handlers, _DeadlineHTTPHandler(deadline),
                                             _DeadlineHTTPSHandler(deadline))
        return opener.open(request, timeout=max(0.001, deadline.remaining()))

    def ask_json(self, text: str, image_urls: Sequence[str] = (),
                 schema: dict[str, Any] | None = None) -> dict[str, Any]:
        """:meth:`complete`, then :func:`extract_json`, then :func:`validate_json` against ``schema``.

        Raises:
            VlmServiceError: as :meth:`complete`.
            VlmAnswerError: the answer holds no JSON object or violates the schema.
        """
        answer = self.complete(text, image_urls)
        try:
            value = extract_json(answer)
        except VlmAnswerError as error:
            raise VlmAnswerError(self.redact(str(error))) from None
        if schema is not None:
            problems = validate_json(value, schema)
            if problems:
                raise VlmAnswerError(self.redact("answer violates the schema: " + "; ".join(problems[:3])))
        return value

    # ------------------------------------------------------------------ messages

    def _tried(self, cause: str, attempt: int) -> str:
        tries = f" (after {attempt + 1} attempts)" if attempt else ""
        return self.redact(f"VLM service at {self.endpoint}: {cause}{tries}")

    def _http_cause(self, error: urllib.error.HTTPError) -> str:
        cause = f"HTTP {error.code} {error.reason}".strip()
        if error.code in (401, 403):
            return cause + " (check the API key)"
        try:
            snippet = error.read(4096).decode("utf-8", "replace")
        except Exception:  # noqa: BLE001 - the body is only decoration of the message
            snippet = ""
        snippet = " ".join(snippet.split())[:SNIPPET_CHARS]
        return f"{cause}: {snippet}" if snippet else cause

    @staticmethod
    def _network_cause(error: BaseException) -> str:
        reason = getattr(error, "reason", error)
        if isinstance(reason, (TimeoutError, socket.timeout)) or isinstance(error, (TimeoutError, socket.timeout)):
            return "timed out"
        if isinstance(reason, ConnectionRefusedError):
            return "connection refused (is the server running?)"
        return f"connection failed: {type(reason).__name__}: {reason}"

    def _content(self, body: bytes) -> str:
        try:
            data = loads_strict(body.decode("utf-8"))
            content = data["choices"][0]["message"]["content"]
        except (UnicodeDecodeError, ValueError, KeyError, IndexError, TypeError, RecursionError):
            snippet = " ".join(body[:SNIPPET_CHARS].decode("utf-8", "replace").split())
            raise VlmAnswerError(self.redact(f"VLM service at {self.endpoint}: not a chat-completions "
                                             f"response: {snippet!r}")) from None
        if isinstance(content, list):  # content parts; only their string "text" fields count
            content = "".join(part["text"] for part in content
                              if isinstance(part, dict) and isinstance(part.get("text"), str))
        if not isinstance(content, str) or not content.strip():
            raise VlmAnswerError(f"VLM service at {self.endpoint}: empty answer")
        return content


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    """Redirects are not followed (urllib would resend the Authorization header to the new
    location); the 3xx surfaces as an HTTPError and fails the request without a retry."""

    def redirect_request(self, req, fp, code, msg, headers, newurl):  # noqa: ANN001 - urllib's signature
        return None


def _retry_after(value: str | None) -> float | None:
    try:
        delay = max(0.0, float(value)) if value is not None else None
    except ValueError:
        return None  # an HTTP date: fall back to the exponential backoff
    return delay if delay is None or math.isfinite(delay) else None


# ---------------------------------------------------------------------- deadline and size cap


class _BodyTooLarge(Exception):
    pass


class _Deadline:
    """One attempt's total time budget. A daemon timer shuts down every socket attached to it when
    the time is up, which ends any blocking connect/recv at once (a server dripping one byte per
    second resets per-read timeouts, not this). Sockets are attached as duplicates of their
    descriptors, so a TLS wrapper that detaches the original does not escape the watchdog."""

    def __init__(self, seconds: float) -> None:
        self.expires = time.monotonic() + seconds
        self.fired = False
        self._sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        self._timer = threading.Timer(seconds, self._fire)
        self._timer.daemon = True
        self._timer.start()

    def remaining(self) -> float:
        return max(0.0, self.expires - time.monotonic())

    def attach(self, sock: socket.socket) -> None:
        try:
            duplicate = sock.dup()
        except OSError:
            return
        with self._lock:
            self._sockets.append(duplicate)
            if self.fired:
                _shutdown(duplicate)

    def _fire(self) -> None:
        with self._lock:
            self.fired = True
            for sock in self._sockets:
                _shutdown(sock)

    def cancel(self) -> None:
        self._timer.cancel()
        with self._lock:
            for sock in self._sockets:
                try:
                    sock.close()
                except OSError:
                    pass
            self._sockets.clear()


def _shutdown(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass


def _deadline_connection(base: type, deadline: _Deadline):
    """An ``http_class`` for urllib's ``do_open``: ``base`` whose TCP socket joins ``deadline``
    as soon as it exists (before any TLS handshake) with its connect timeout cut to what is left."""

    def make(host: str, **kwargs):
        connection = base(host, **kwargs)
        create = connection._create_connection

        def create_under_deadline(address, timeout=None, source_address=None):
            sock = create(address, max(0.001, deadline.remaining()), source_address)
            deadline.attach(sock)
            return sock

        connection._create_connection = create_under_deadline
        return connection

    return make


class _DeadlineHTTPHandler(urllib.request.HTTPHandler):
    def __init__(self, deadline: _Deadline) -> None:
        super().__init__()
        self._deadline = deadline

    def http_open(self, req):  # noqa: ANN001 - urllib's signature
        return self.do_open(_deadline_connection(http.client.HTTPConnection, self._deadline), req)


class _DeadlineHTTPSHandler(urllib.request.HTTPSHandler):
    def __init__(self, deadline: _Deadline) -> None:
        super().__init__()
        self._deadline = deadline

    def https_open(self, req):  # noqa: ANN001 - urllib's signature
        return self.do_open(_deadline_connection(http.client.HTTPSConnection, self._deadline), req,
                            context=self._context)


def _read_capped(response, deadline: _Deadline) -> bytes:
    """The response body, at most ``MAX_BODY_BYTES``; raises TimeoutError when the deadline cut
    it short and _BodyTooLarge beyond the cap (a declared Content-Length is checked first)."""
    declared = response.headers.get("Content-Length") if response.headers else None
    if declared is not None and declared.strip().isdigit() and int(declared) > MAX_BODY_BYTES:
        raise _BodyTooLarge(f"response body of {int(declared)} bytes exceeds the limit of {MAX_BODY_BYTES}")
    body = response.read(MAX_BODY_BYTES + 1)
    if deadline.fired:
        raise TimeoutError("deadline passed while reading the response")
    if len(body) > MAX_BODY_BYTES:
        raise _BodyTooLarge(f"response body exceeds the limit of {MAX_BODY_BYTES} bytes")
    return body


# ---------------------------------------------------------------------- strict JSON


class _JsonLimit(ValueError):
    pass


def _reject_constant(name: str):
    raise _JsonLimit(f"non-finite number {name}")


def _parse_int(text: str) -> int | float:
    return int(text) if len(text.lstrip("-")) <= 18 else float(text)   # huge -> float (maybe inf)


def _parse_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise _JsonLimit(f"number {text[:20]} is too large")
    return value


def json_depth(text: str) -> int:
    """Maximum ``[``/``{`` nesting of JSON text (strings skipped), without parsing. O(n)."""
    from sparseart.io.validate import json_nesting_depth

    return json_nesting_depth(text.encode("utf-8", "surrogatepass"))


def loads_strict(text: str, max_depth: int = MAX_JSON_DEPTH):
    """``json.loads`` that refuses nesting deeper than ``max_depth``, NaN/Infinity and numbers
    beyond float range. Raises ValueError (incl. json.JSONDecodeError)."""
    if json_depth(text) > max_depth:
        raise _JsonLimit(f"JSON nested more than {max_depth} levels")
    try:
        value = json.loads(text, parse_constant=_reject_constant, parse_int=_parse_int, parse_float=_parse_float)
    except RecursionError:
        raise _JsonLimit(f"JSON nested more than {max_depth} levels") from None
    if isinstance(value, float) and not math.isfinite(value):
        raise _JsonLimit("non-finite number")
    return value


# ---------------------------------------------------------------------- answers

_FENCE = re.compile(r"```[ \t]*(?:json|JSON)?[ \t]*\n?(.*?)```", re.DOTALL)


def extract_json(text: str) -> dict[str, Any]:
    """The JSON object in a model's answer.

    Tries, in order: the whole text; the body of every ```json (or bare ```) fence; the first
    ``{`` from which a JSON object decodes (prose before or after it is ignored). O(len(text)) per
    candidate start; the text is cut at ``MAX_ANSWER_CHARS``.

    Raises:
        VlmAnswerError: no JSON object found (the message quotes the answer's start).
    """
    text = text[:MAX_ANSWER_CHARS]
    if json_depth(text) > MAX_JSON_DEPTH:
        raise VlmAnswerError(f"answer nests brackets more than {MAX_JSON_DEPTH} levels deep")
    candidates = [text.strip(), *(m.group(1).strip() for m in _FENCE.finditer(text))]
    for candidate in candidates:
        try:
            value = loads_strict(candidate)
        except ValueError:
            continue
        if isinstance(value, dict) and _all_finite(value):
            return value
    decoder = json.JSONDecoder(parse_constant=_reject_constant, parse_int=_parse_int, parse_float=_parse_float)
    for match in re.finditer(r"\{", text):
        try:
            value, _ = decoder.raw_decode(text, match.start())
        except (ValueError, RecursionError):
            continue
        if isinstance(value, dict) and _all_finite(value):
            return value
    snippet = " ".join(text.split())[:80]
    raise VlmAnswerError(f"answer holds no JSON object: {snippet!r}")


def _all_finite(value: Any, depth: int = 0) -> bool:
    """No float in ``value`` is NaN or infinite (a huge integer became ``inf`` when parsed)."""
    if depth > MAX_JSON_DEPTH:
        return False
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, dict):
        return all(_all_finite(v, depth + 1) for v in value.values())
    if isinstance(value, list):
        return all(_all_finite(v, depth + 1) for v in value)
    return True


_TYPES: dict[str, Callable[[Any], bool]] = {
    "object": lambda v: isinstance(v, dict),
    "array": lambda v: isinstance(v, list),
    "string": lambda v: isinstance(v, str),
    "integer": lambda v: ((isinstance(v, int) and not isinstance(v, bool))
                          or (isinstance(v, float) and math.isfinite(v) and v.is_integer())),
    "number": lambda v: (isinstance(v, int) and not isinstance(v, bool)) or (isinstance(v, float) and math.isfinite(v)),
    "boolean": lambda v: isinstance(v, bool),
    "null": lambda v: v is None,
}
SUPPORTED_KEYWORDS = frozenset({"type", "properties", "required", "enum", "items", "minimum", "maximum",
                                "additionalProperties", "minItems", "maxItems", "description", "title"})


def validate_json(value: Any, schema: dict[str, Any], path: str = "$") -> list[str]:
    """Problems of ``value`` against ``schema`` (empty list = valid), each naming its JSON path.

    Supports the subset of JSON Schema the prompt schemas use: ``type`` (name or list),
    ``properties``, ``required``, ``additionalProperties`` (bool or schema), ``items`` (one schema),
    ``enum``, ``minimum``/``maximum``, ``minItems``/``maxItems``. As in JSON Schema draft 6+, an
    integral float (2.0) is an integer; a bool is not a number, nor is NaN or an infinity. Nesting
    deeper than ``MAX_JSON_DEPTH`` is a problem, not a RecursionError. O(size of value).

    Raises:
        ValueError: the schema uses a keyword outside the subset (a schema bug, not an answer bug).
    """
    if path.count(".") + path.count("[") > MAX_JSON_DEPTH:
        return [f"{path}: nested more than {MAX_JSON_DEPTH} levels"]
    unknown = set(schema) - SUPPORTED_KEYWORDS
    if unknown:
        raise ValueError(f"schema at {path} uses unsupported keyword(s) {sorted(unknown)}")
    problems: list[str] = []
    kinds = schema.get("type")
    if kinds is not None:
        names = [kinds] if isinstance(kinds, str) else list(kinds)
        if not any(_TYPES[name](value) for name in names):
            return [f"{path}: expected {' or '.join(names)}, got {type(value).__name__}"]
    if "enum" in schema and value not in schema["enum"]:
        problems.append(f"{path}: {value!r} is not one of {schema['enum']}")
    if _TYPES["number"](value):
        if "minimum" in schema and value < schema["minimum"]:
            problems.append(f"{path}: {value} < minimum {schema['minimum']}")
        if "maximum" in schema and value > schema["maximum"]:
            problems.append(f"{path}: {value} > maximum {schema['maximum']}")
    if isinstance(value, dict):
        properties = schema.get("properties", {})
        for name in schema.get("required", []):
            if name not in value:
                problems.append(f"{path}: missing required {name!r}")
        extra = schema.get("additionalProperties", True)
        for name, item in value.items():
            if name in properties:
                problems += validate_json(item, properties[name], f"{path}.{name}")
            elif extra is False:
                problems.append(f"{path}: unexpected property {name!r}")
            elif isinstance(extra, dict):
                problems += validate_json(item, extra, f"{path}.{name}")
    if isinstance(value, list):
        if "minItems" in schema and len(value) < schema["minItems"]:
            problems.append(f"{path}: fewer than {schema['minItems']} items")
        if "maxItems" in schema and len(value) > schema["maxItems"]:
            problems.append(f"{path}: more than {schema['maxItems']} items")
        if isinstance(schema.get("items"), dict):
            for index, item in enumerate(value):
                problems += validate_json(item, schema["items"], f"{path}[{index}]")
    return problems
