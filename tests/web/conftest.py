"""The API tests' fixtures (a real ScanLoop on virtual time behind a real ApiServer)."""

from tests.api.conftest import api, plc_parts, scan  # noqa: F401 - pytest fixtures
