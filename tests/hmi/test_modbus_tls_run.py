"""Modbus/TCP Security wired into `softplc run` (--modbus-tls HOST:PORT): a process of its
own beside the plain slave, its certificate made at the first start in the state directory,
an operator's certificate accepted with `softplc`'s trust directory and its coil write
reaching the running program's image; a viewer's refused with 01 (issue 31)."""

from __future__ import annotations

from pathlib import Path

from pymodbus.client import ModbusTlsClient

from softplc.api import trustcmds
from softplc.api.client import ApiClient
from softplc.cli import main
from softplc.hmi.secure import MODBUS_TLS_DIR
from softplc.runtime.serve.comm import CommConfig, service_groups
from tests.hmi.test_modbus_tls import client_context, make_client
from tests.support import eventually, free_port, softplc_run


def test_the_secure_slave_has_a_process_of_its_own() -> None:
    assert trustcmds.MODBUS_TLS_DIR == MODBUS_TLS_DIR  # `softplc trust --modbus` finds it
    groups = service_groups(CommConfig(modbus_tls=("127.0.0.1", 802)))
    assert list(groups) == ["modbus", "modbus-tls", "http"]
    assert groups["modbus-tls"].modbus is None and groups["modbus-tls"].api is None
    assert groups["modbus-tls"].modbus_tls == ("127.0.0.1", 802)


def test_softplc_run_serves_modbus_tls_with_roles_from_certificates(tmp_path: Path) -> None:
    state, api_port, tls_port = tmp_path / "state", free_port(), free_port()
    server_cert = state / MODBUS_TLS_DIR / "tls" / "cert.pem"
    api = ApiClient(f"http://127.0.0.1:{api_port}", state_dir=state, timeout_s=10)
    with softplc_run(["programs/transport.yaml", "--plant", "transport", "--api",
                      f"127.0.0.1:{api_port}", "--modbus", "off", "--opcua", "off",
                      "--modbus-tls", f"127.0.0.1:{tls_port}", "--state-dir", str(state),
                      "--quiet"], lambda: server_cert.exists() and api.status()):
        operator = make_client(tmp_path / "clients", "hmi-op", "operator")
        viewer = make_client(tmp_path / "clients", "hmi-view", "viewer")
        for client in (operator, viewer):  # the admin's command
            assert main(["trust", "accept", str(client.cert), "--modbus", "--state-dir",
                         str(state)]) == 0
        assert main(["trust", "list", "--modbus", "--state-dir", str(state)]) == 0
        for client, refused in ((viewer, True), (operator, False)):
            modbus = ModbusTlsClient("127.0.0.1", port=tls_port, timeout=5, retries=0,
                                     sslctx=client_context(server_cert, client))
            assert eventually(modbus.connect, 30, "the secure slave accepts the client")
            try:
                written = modbus.write_coil(800, True, device_id=1)  # hold := 1 (%MX0.0)
                assert written.isError() is refused, written
                if refused:
                    assert written.exception_code == 1
            finally:
                modbus.close()
        assert eventually(lambda: api.read_symbol("hold") is True, 10, "hold written")
