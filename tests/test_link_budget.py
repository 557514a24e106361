"""Link-limit arithmetic against the figures quoted for real buses."""

from __future__ import annotations

import pytest

from servobench.drivers.link_budget import (
    can_frame_bits,
    canopen_cycle_s,
    modbus_rtu_cycle_s,
    modbus_rtu_frames,
    modbus_tcp_cycle_s,
    uart_cycle_s,
)


def test_can_frame_bits_with_and_without_stuffing():
    assert can_frame_bits(0) == 47 and can_frame_bits(8) == 111
    assert can_frame_bits(0, True) == 55 and can_frame_bits(8, True) == 135


def test_canopen_reference_cycle_is_237_to_285_us():
    best, worst = canopen_cycle_s([0, 4, 8], bitrate=1e6)
    assert (best, worst) == pytest.approx((237e-6, 285e-6))


def test_modbus_rtu_fc23_and_write_then_read_at_115200():
    # Modbus RTU characters are 11 bits (8 data, parity or a second stop bit): 157/s and ~90/s.
    fc23 = modbus_rtu_cycle_s(modbus_rtu_frames(2, 4, fc23=True), 115200, bits_per_char=11)
    two = modbus_rtu_cycle_s(modbus_rtu_frames(2, 4, fc23=False), 115200, bits_per_char=11)
    assert modbus_rtu_frames(2, 4, fc23=True) == [17, 13]
    assert 1 / fc23 == pytest.approx(157, rel=0.03)
    assert 1 / two == pytest.approx(90, rel=0.02)
    assert modbus_rtu_cycle_s([8], 9600) == pytest.approx(8 * 10 / 9600 + 3.5 * 11 / 9600)


def test_tcp_and_uart():
    # 54 bytes of Ethernet/IP/TCP headers + FCS around each ADU, then preamble and gap
    assert modbus_tcp_cycle_s([27, 17]) == pytest.approx((85 + 20 + 75 + 20) * 8 / 100e6)
    assert modbus_tcp_cycle_s([1]) == pytest.approx((64 + 20) * 8 / 100e6)  # padded
    assert uart_cycle_s(33, 115200) == pytest.approx(33 * 10 / 115200)
