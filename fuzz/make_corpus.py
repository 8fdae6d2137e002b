#!/usr/bin/env python3
"""Builds the seed corpora of the fuzz targets from the captured wire traces and the Annex B
vectors. Run from the repository root: python3 fuzz/make_corpus.py"""
import hashlib, pathlib, re, struct

root = pathlib.Path(__file__).resolve().parent.parent
traces = sorted((root / "common/tests/data/wire-traces").glob("*.txt"))
out = root / "fuzz/corpus"
annex_b = [
    "80 00 00 00 00 01 0E 00 58 52 43 45 01 00 0F 0F 22 33 44 55 DD 00",
    "DD 80 01 00 07 09 10 00 AA 01 44 05 04 00 00 00 14 00 11 00 1A 00 28 00",
    "DD 80 01 00 07 03 0E 00 AA 01 44 05 00 02 00 00 E8 03 00 00 19 00",
    "DD 80 01 00 07 03 0C 00 AA 01 44 05 02 00 11 22 33 64 19 00",
    "DD 01 01 00 09 02 14 00 AA 02 44 06 00 03 00 00 00 00 00 01 00 00 03 E8 00 00 00 01",
    "DD 01 01 00 09 0A 28 00 AA 02 44 06 00 00 00 02 00 03 00 00 00 00 00 01 00 00 03 E8 00 00 00 01"
    " 00 03 00 00 00 00 00 02 00 00 04 4C 00 00 00 01",
    "DD 80 01 00 09 0E 24 00 AA 03 44 06 00 03 00 00 00 00 00 01 00 00 03 E8 00 00 00 02 00 00 00 00"
    " 00 00 00 01 00 01 00 01 00 00 00 01",
    "DD 80 01 00 08 01 20 00 AA 01 44 06 00 08 01 00 06 00 00 00 78 3E 31 30 30 00 01 00 08 00 00 00"
    " 64 00 1E 00 00 04 E8 03",
]


def write(kind, data):
    d = out / kind
    d.mkdir(parents=True, exist_ok=True)
    (d / hashlib.sha1(data).hexdigest()[:16]).write_bytes(data)


per_client = {}
for t in traces:
    for line in t.read_text().splitlines():
        parts = line.split()
        if len(parts) != 4 or parts[1] not in ("C>A", "A>C"):
            continue
        data = bytes.fromhex(parts[3])
        write("decode", data)
        for xml in re.findall(rb"<dds>.*?</dds>", data, re.S):
            write("representations", xml)
        if parts[1] == "C>A":
            per_client.setdefault((t.stem, parts[2]), []).append(data)
for v in annex_b:
    write("decode", bytes.fromhex(v.replace(" ", "")))
for (stem, port), datagrams in per_client.items():
    blob = b""
    for i, d in enumerate(datagrams):
        piece = struct.pack("<HB", len(d), 0) + d
        if len(blob) + len(piece) > 16384:
            write("agent_session", blob)
            blob = b""
        blob += piece
    if blob:
        write("agent_session", blob)
for f in sorted((root / "tests/data").glob("*.refs")):
    write("representations", f.read_bytes())
# Type documents (keys, nesting, typedefs, enums) for the type and filter parsers.
for doc in (
    b'<dds><types><module name="M"><const name="N" type="int32" value="8"/>'
    b'<enum name="C"><enumerator name="R"/><enumerator name="G" value="4"/></enum>'
    b'<struct name="P"><member name="x" type="float64"/><member name="c" type="nonBasic" nonBasicTypeName="C"/></struct>'
    b'<struct name="S"><member name="id" type="string" key="true" stringMaxLength="N"/>'
    b'<member name="p" type="nonBasic" nonBasicTypeName="P" arrayDimensions="2,3"/>'
    b'<member name="v" type="int16" sequenceMaxLength="-1"/></struct></module></types></dds>',
    b'<types><type><struct name="B"><member name="k" type="uint64" key="true"/></struct></type>'
    b'<type><struct name="D" baseType="B"><member name="s" type="string" sequenceMaxLength="4"/></struct></type>'
    b'<typedef name="A" type="nonBasic" nonBasicTypeName="D"/></types>',
):
    write("representations", doc)
# Byte streams for the framers: the serial hexdump per direction and the TCP pcap's
# payloads per direction, each with a leading chunking seed byte, plus cuts of them.
hexdump = (root / "common/tests/data/wire-traces/serial-ping-and-ref-creation.hexdump.txt").read_text()
streams = {"<": b"", ">": b""}
lines = hexdump.splitlines()
for i, line in enumerate(lines):
    if line[:1] in streams and i + 1 < len(lines):
        streams[line[:1]] += bytes.fromhex(lines[i + 1])
for direction, stream in streams.items():
    for seed in (1, 77, 200):
        write("serial_framing", bytes([seed]) + stream)
    for cut in range(0, len(stream), 97):
        write("serial_framing", bytes([cut % 251]) + stream[cut:cut + 300])


def pcap_tcp_payloads(path):
    """TCP payloads of an Ethernet/IPv4 pcap, as (source port, bytes), in order."""
    data = path.read_bytes()
    off, out = 24, []
    while off + 16 <= len(data):
        incl = struct.unpack_from("<I", data, off + 8)[0]
        pkt = data[off + 16:off + 16 + incl]
        off += 16 + incl
        if len(pkt) < 34 or pkt[12:14] != b"\x08\x00" or pkt[23] != 6:
            continue
        ihl = (pkt[14] & 0x0F) * 4
        total = struct.unpack_from(">H", pkt, 16)[0]
        tcp = pkt[14 + ihl:14 + total]
        payload = tcp[(tcp[12] >> 4) * 4:]
        if payload:
            out.append((struct.unpack_from(">H", tcp, 0)[0], payload))
    return out


segments = pcap_tcp_payloads(root / "common/tests/data/wire-traces/tcp-ping-and-ref-creation.pcap")
for port in sorted({p for p, _ in segments}):
    stream = b"".join(s for p, s in segments if p == port)
    for seed in (3, 91, 250):
        write("tcp_framing", bytes([seed]) + stream)
    for cut in range(0, len(stream), 61):
        write("tcp_framing", bytes([cut % 251]) + stream[cut:cut + 200])
for kind in ("decode", "agent_session", "representations", "serial_framing", "tcp_framing"):
    print(kind, len(list((out / kind).iterdir())))
