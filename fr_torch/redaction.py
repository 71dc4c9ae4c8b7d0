"""Secrets in URLs never leave the process: the one redaction of every URL fR prints, logs or writes.

An IP camera's URL often carries its credentials: in the user part (``rtsp://admin:pass@host/``)
or in the query string (``http://host/videostream.cgi?user=admin&pwd=secret``,
``rtsp://host/live?token=...``).  :func:`redact_url` turns such a URL into the text fR shows
anywhere (messages, ``calibration.json``, records, metrics): the password of the user part becomes
``***`` (the user name stays; a user part without a password, which may be a token, becomes
``***`` whole), and so does the value of every query or fragment parameter whose
name says it is a credential (:data:`SECRET_NAME`: it contains ``pass``, ``pwd``, ``token``,
``key``, ``auth``, ``sig``, ``secret``, ``cred``, ``session``, ``sid``, ``ticket``, ``jwt`` or
``otp``; case-insensitive, the name percent-decoded first).  Everything else is kept as written,
so the text still says which camera it is.

:func:`redact_text` applies :func:`redact_url` to every ``scheme://`` URL inside a longer text
(an error message that quotes a URL): the guard of the command line's error line.
"""
from __future__ import annotations

import re
from urllib.parse import unquote

#: What a hidden secret is shown as.
MASK = "***"
#: A query or fragment parameter name that says its value is a credential (searched, case-insensitive,
#: in the percent-decoded name): ``pwd``, ``password``, ``passwd``, ``token``, ``access_token``,
#: ``key``, ``apikey``, ``auth``, ``authorization``, ``sig``, ``signature``, ``secret``, ``credential``,
#: ``session``, ``sid``, ``ticket``, ``jwt``, ``otp``, ...
SECRET_NAME = re.compile(r"pass|pwd|token|key|auth|sig|secret|cred|session|sid|ticket|jwt|otp", re.IGNORECASE)
#: A URL in a text: a scheme, ``://`` and what follows up to white space or a quote, less a
#: sentence's closing punctuation.
URL = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*://[^\s'\"<>`]*[^\s'\"<>`.,;:)\]]")
#: The start of a ``scheme://`` URL (a stream's address, not a file path).
SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")


def secret_name(name: str) -> bool:
    """True when a URL parameter called ``name`` (percent-encoded or not) holds a credential."""
    return bool(SECRET_NAME.search(unquote(name.replace("+", " "))))


def _parameters(text: str) -> str:
    """A query string (or fragment) with the value of each credential parameter masked; ``&`` and
    ``;`` separate parameters, each ``name=value`` or a bare ``name``."""
    parts = re.split(r"([&;])", text)
    for i in range(0, len(parts), 2):
        name, equals, value = parts[i].partition("=")
        if equals and value and secret_name(name):
            parts[i] = f"{name}={MASK}"
    return "".join(parts)


def redact_url(url: str) -> str:
    """``url`` as fR shows it (module docstring): the user part's password and every credential
    parameter's value replaced by ``***``.  Text that is no ``scheme://`` URL comes back unchanged.

    >>> redact_url("rtsp://admin:hunter2@10.0.0.5:554/live?channel=1&token=abc")
    'rtsp://admin:***@10.0.0.5:554/live?channel=1&token=***'
    """
    match = SCHEME.match(url)
    if not match:
        return url
    scheme, rest = match.group(0), url[match.end():]
    # the user part ends at the last "@" before the query: a password may hold an unencoded "/" or "@"
    before_query = re.split(r"[?#]", rest, maxsplit=1)[0]
    user_end = before_query.rfind("@") + 1
    authority_end = len(rest)
    for mark in "/?#":
        at = rest.find(mark, user_end)
        if at >= 0:
            authority_end = min(authority_end, at)
    authority, tail = rest[:authority_end], rest[authority_end:]
    userinfo, at, hostport = authority.rpartition("@")
    if at:
        user, colon, _ = userinfo.partition(":")
        authority = f"{user}:{MASK}@{hostport}" if colon else f"{MASK}@{hostport}"
    path, hash_, fragment = tail.partition("#")
    path, question, query = path.partition("?")
    tail = path + (question + _parameters(query) if question else "") + (hash_ + _parameters(fragment) if hash_ else "")
    return scheme + authority + tail


def redact_text(text: str) -> str:
    """``text`` with every URL in it redacted (:func:`redact_url`)."""
    return URL.sub(lambda match: redact_url(match.group(0)), text)
