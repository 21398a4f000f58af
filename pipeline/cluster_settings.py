"""What every kind of cluster is started with, for :mod:`pipeline.cluster` (a LocalCluster, a scheduler)
and :mod:`pipeline.jobs` (batch jobs) alike: the dashboard's binding, the module every worker imports
first, and ``cluster.security`` as distributed's TLS settings (a ``Security``)."""
from __future__ import annotations

import os
import ssl

from pipeline.config import SECURITY_FILES, check_security
from pipeline.errors import ConfigError


PRELOAD = "pipeline.worker_init"   # every worker imports it first (see that module); `dask worker --preload`
LOCALHOST = "127.0.0.1"
# A scheduler always serves its HTTP routes (/health, /metrics), dashboard or not, and distributed puts
# them on 8787 unless told otherwise: with ``dashboard_address: null`` they go to a free local port, so a
# run without a dashboard never takes the port of another run's dashboard.
NO_DASHBOARD = {"dashboard": False, "dashboard_address": f"{LOCALHOST}:0"}


def dashboard_bind(address: str | None) -> str | None:
    """``cluster.dashboard_address`` as bound: one without a host (``:8787``, ``8787``) on 127.0.0.1,
    so the dashboard is not open to the network unless an interface is named (``0.0.0.0:8787``)."""
    if address is None:
        return None
    a = str(address).strip()
    if a.startswith(":") or a.isdigit():
        return f"{LOCALHOST}:{a.lstrip(':')}"
    return a


def make_security(sec, where: str = "dataset.cluster.security"):
    """``cluster.security`` -> ``distributed.security.Security`` (None when not set). Paths may use
    ``~`` and ``$VARS``; each must name a readable file on this machine. ``require_encryption``
    defaults to true: every connection is TLS, a ``tcp://`` address is refused."""
    if sec is None:
        return None
    check_security(sec, where)
    from distributed.security import Security
    kw = {"require_encryption": sec.get("require_encryption", True)}
    for k in SECURITY_FILES:
        if sec.get(k):
            path = os.path.expandvars(os.path.expanduser(sec[k]))
            if not os.path.isfile(path) or not os.access(path, os.R_OK):
                raise ConfigError(f"{where}.{k}: cannot read {path!r} (no such file, or not readable); give the "
                                  "path of the PEM file on this machine")
            kw[k] = path
    if sec.get("tls_ciphers"):
        kw["tls_ciphers"] = sec["tls_ciphers"]
    for k in ("tls_min_version", "tls_max_version"):
        if sec.get(k):
            kw[k] = ssl.TLSVersion[sec[k]]
    return Security(**kw)
