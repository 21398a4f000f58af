"""pipeline.cluster: the dashboard binds to 127.0.0.1 unless an interface is named, and
``cluster.security`` becomes distributed's TLS ``Security`` (a bad one is a clear error before any
connection; a good one reaches a TLS scheduler, which a plain client cannot)."""
from __future__ import annotations

import shutil
import ssl
import subprocess
from pathlib import Path

import pytest
import yaml

from pipeline import cluster as cl, cluster_settings as cs
from pipeline.config import ClusterConfig, DatasetConfig, load_config
from pipeline.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("given, bound", [
    (":8787", "127.0.0.1:8787"), ("8787", "127.0.0.1:8787"), (":0", "127.0.0.1:0"),
    ("127.0.0.1:8787", "127.0.0.1:8787"), ("0.0.0.0:8787", "0.0.0.0:8787"), (None, None)])
def test_dashboard_without_a_host_binds_to_localhost(given, bound):
    assert cs.dashboard_bind(given) == bound


def test_shipped_defaults_keep_the_dashboard_on_this_machine():
    assert ClusterConfig().dashboard_address == "127.0.0.1:8787"
    assert load_config(ROOT / "configs/default.yaml").cluster.dashboard_address == "127.0.0.1:8787"
    assert load_config(ROOT / "configs/smoke.yaml").cluster.dashboard_address == "127.0.0.1:0"


def test_local_cluster_dashboard_listens_on_localhost_only():
    conn = cl.connect(ClusterConfig(dashboard_address=":0", workers=1))
    try:
        sockets = conn.cluster.scheduler.http_server._sockets.values()
        assert {s.getsockname()[0] for s in sockets} == {"127.0.0.1"}
        assert conn.dashboard.startswith("http://127.0.0.1:")
    finally:
        conn.close()


@pytest.fixture(scope="module")
def tls_dir(tmp_path_factory):
    """A self-signed certificate (its own CA) and key, made with the openssl command."""
    if shutil.which("openssl") is None:
        pytest.skip("needs the openssl command to make a test certificate")
    d = tmp_path_factory.mktemp("tls")
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=dask-test",
                    "-addext", "basicConstraints=critical,CA:TRUE", "-keyout", str(d / "node-key.pem"),
                    "-out", str(d / "node.pem")], check=True, capture_output=True, timeout=60)
    shutil.copy(d / "node.pem", d / "ca.pem")
    return d


def _sec(d) -> dict:
    return {"tls_ca_file": str(d / "ca.pem"), "tls_client_cert": str(d / "node.pem"),
            "tls_client_key": str(d / "node-key.pem")}


@pytest.mark.parametrize("bad, message", [
    ("not a mapping", r"dataset\.cluster\.security must be a mapping of distributed TLS settings"),
    ({"tls_ca": "x"}, r"dataset\.cluster\.security: unknown key\(s\) \['tls_ca'\]; known: \['require_encryption'"),
    ({"tls_client_cert": "c.pem"}, r"dataset\.cluster\.security\.tls_ca_file must be set"),
    ({"tls_ca_file": "ca.pem"}, r"dataset\.cluster\.security\.tls_client_cert must be set"),
    ({"tls_ca_file": "ca.pem", "tls_client_cert": 3}, r"tls_client_cert must be a file path \(a string\), got 3"),
    ({"tls_ca_file": "a", "tls_client_cert": "b", "require_encryption": "yes"}, r"require_encryption must be true or false"),
    ({"tls_ca_file": "a", "tls_client_cert": "b", "tls_min_version": "SSLv3"}, r"tls_min_version must be one of"),
])
def test_bad_security_config_is_refused_when_loaded(tmp_path, bad, message):
    d = yaml.safe_load((ROOT / "configs/smoke.yaml").read_text())
    d["cluster"]["security"] = bad
    with pytest.raises(ConfigError, match=message):
        DatasetConfig.from_dict(d)


def test_missing_certificate_file_is_named(tls_dir, tmp_path):
    sec = {**_sec(tls_dir), "tls_client_key": str(tmp_path / "nope.pem")}
    with pytest.raises(ConfigError, match=r"dataset\.cluster\.security\.tls_client_key: cannot read '.*nope\.pem'"):
        cs.make_security(sec)


def test_good_security_config_builds_a_security_object(tls_dir, monkeypatch):
    from distributed.security import Security
    assert cs.make_security(None) is None
    sec = cs.make_security({**_sec(tls_dir), "tls_min_version": "TLSv1_3"})
    assert isinstance(sec, Security) and sec.require_encryption is True
    assert (sec.tls_ca_file, sec.tls_client_cert) == (str(tls_dir / "ca.pem"), str(tls_dir / "node.pem"))
    assert sec.tls_min_version == ssl.TLSVersion.TLSv1_3
    assert sec.get_connection_args("client")["ssl_context"] is not None     # the files really load
    # the shipped example: paths under $DASK_TLS_DIR
    monkeypatch.setenv("DASK_TLS_DIR", str(tls_dir))
    cfg = load_config(ROOT / "configs/cluster-scheduler.yaml").cluster
    assert cfg.address.startswith("tls://")
    assert cs.make_security(cfg.security).tls_client_key == str(tls_dir / "node-key.pem")


def test_tls_scheduler_is_reached_with_security_and_refuses_plain_tcp(tls_dir):
    from distributed import LocalCluster
    from distributed.security import Security
    pem, key = str(tls_dir / "node.pem"), str(tls_dir / "node-key.pem")
    server = Security(tls_ca_file=str(tls_dir / "ca.pem"), tls_scheduler_cert=pem, tls_scheduler_key=key,
                      tls_worker_cert=pem, tls_worker_key=key, tls_client_cert=pem, tls_client_key=key,
                      require_encryption=True)
    with LocalCluster(n_workers=0, processes=False, host="tls://127.0.0.1", dashboard_address="127.0.0.1:0",
                      security=server) as shared:
        addr = shared.scheduler_address
        assert addr.startswith("tls://")
        conn = cl.connect(ClusterConfig(kind="scheduler", address=addr, security=_sec(tls_dir), connect_timeout=10))
        try:
            assert conn.address == addr and conn.n_workers() == 0
        finally:
            conn.close()
        host_port = addr.split("://", 1)[1]
        conn = cl.connect(ClusterConfig(kind="scheduler", address="tls://" + host_port, security=_sec(tls_dir)),
                          scheduler=host_port)           # no scheme: tls:// when security is set
        conn.close()
        with pytest.raises(ConfigError, match=r"requires encryption, but the scheduler address is tcp://"):
            cl.connect(ClusterConfig(kind="scheduler", address="tcp://" + host_port, security=_sec(tls_dir)))
        with pytest.raises(cl.ClusterError, match="cannot reach the Dask scheduler"):
            cl.connect(ClusterConfig(kind="scheduler", address="tcp://" + host_port, connect_timeout=2))
