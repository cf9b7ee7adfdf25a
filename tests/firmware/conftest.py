"""The one flight two firmware test files read (tests/support/stock_flight.py): flown once per
session, on the first test that asks for it; skipped, as those tests are, without the firmware."""
import pytest


@pytest.fixture(scope="session")
def stock_flight(tmp_path_factory):
    from tests.support.stock_flight import fly_stock
    return fly_stock(tmp_path_factory.mktemp("ardupilot_stock"))
