"""The Fast DDS profiles: the shipped one (``config/fastdds_shm.xml``) and the tests' one parse,
carry shared memory for large clouds and keep UDP on loopback (nothing leaves the machine)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

NS = {'p': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize('path', ['config/fastdds_shm.xml', 'test/fastdds_localhost.xml'])
def test_profile_is_shared_memory_plus_loopback_udp_only(path: str) -> None:
    root = ET.parse(ROOT / path).getroot()
    transports = {
        t.findtext('p:transport_id', namespaces=NS): t
        for t in root.iterfind('p:transport_descriptors/p:transport_descriptor', NS)
    }
    kinds = {name: t.findtext('p:type', namespaces=NS) for name, t in transports.items()}
    assert sorted(kinds.values()) == ['SHM', 'UDPv4'], kinds
    for t in transports.values():
        if t.findtext('p:type', namespaces=NS) == 'UDPv4':
            allowed = [a.text for a in t.iterfind('p:interfaceWhiteList/p:address', NS)]
            assert allowed == ['127.0.0.1']
        else:
            # Room for several clouds of a 128-beam LiDAR (~4 MB each) in flight.
            assert int(t.findtext('p:segment_size', namespaces=NS) or 0) >= 16 * 2**20
    participants = root.findall('p:participant', NS)
    assert len(participants) == 1
    assert participants[0].get('is_default_profile') == 'true'
    rtps = participants[0].find('p:rtps', NS)
    assert rtps is not None
    # The built-in transports (UDP on every interface) are off; only the two above are used.
    assert rtps.findtext('p:useBuiltinTransports', namespaces=NS) == 'false'
    used = [u.text for u in rtps.iterfind('p:userTransports/p:transport_id', NS)]
    assert sorted(used) == sorted(transports)


def test_the_shipped_profile_is_installed() -> None:
    setup = (ROOT / 'setup.py').read_text()
    assert "glob('config/*.xml')" in setup
