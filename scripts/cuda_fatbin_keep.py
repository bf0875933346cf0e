#!/usr/bin/env python3
"""Keep only some GPU architectures' kernels in a CUDA shared library (for scripts/gpu-bundle.sh).

    python3 scripts/cuda_fatbin_keep.py LIB OUT --arch 90 [--arch 100 ...]

Writes a copy of LIB to OUT in which every kernel image (cubin or PTX) of the `.nv_fatbin`
section built for another architecture is zeroed: the headers stay as they were, so the CUDA
driver still finds the images of the kept architectures where it looked before, and the zeroed
bytes compress to almost nothing. ONNX Runtime's CUDA provider (284 MB, 218 MB of it kernels for
six architectures) then packs small enough to travel to a machine that cannot download it.

Bad input (not an ELF file, no `.nv_fatbin` section, a fatbin layout this script does not know,
nothing of the kept architectures in it) is one line on stderr and exit status 1; OUT is then not
written. Standard library only.
"""
import argparse
import os
import struct
import sys

FATBIN_MAGIC = 0xBA55ED50


def die(msg):
    print(f"cuda_fatbin_keep: {msg}", file=sys.stderr)
    sys.exit(1)


def fatbin_section(data):
    """(offset, size) of `.nv_fatbin` in an ELF64 little-endian file."""
    if data[:4] != b"\x7fELF" or data[4] != 2 or data[5] != 1:
        raise ValueError("not a 64-bit little-endian ELF file")
    shoff, = struct.unpack_from("<Q", data, 0x28)
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", data, 0x3A)
    if shoff == 0 or shnum == 0 or shoff + shnum * shentsize > len(data) or shstrndx >= shnum:
        raise ValueError("no section headers")

    def header(i):
        name, _type, _flags, _addr, off, size = struct.unpack_from("<IIQQQQ", data, shoff + i * shentsize)
        return name, off, size

    _, str_off, str_size = header(shstrndx)
    for i in range(shnum):
        name, off, size = header(i)
        end = data.find(b"\0", str_off + name, str_off + str_size)
        if data[str_off + name:end] == b".nv_fatbin":
            if off + size > len(data):
                raise ValueError(".nv_fatbin runs past the end of the file")
            return off, size
    raise ValueError("no .nv_fatbin section (not a CUDA library?)")


def prune(data, keep):
    """Zero the images of architectures not in `keep`, in place; returns per-arch byte counts."""
    off, size = fatbin_section(data)
    pos, end = off, off + size
    kept, zeroed, containers = {}, {}, 0
    while pos + 16 <= end:
        magic, _version, hsz, fsz = struct.unpack_from("<IHHQ", data, pos)
        if magic != FATBIN_MAGIC:
            pos += 8  # containers are 8-byte aligned, padding between them
            continue
        containers += 1
        e, cend = pos + hsz, pos + hsz + fsz
        if cend > end:
            raise ValueError(f"fatbin container at {pos:#x} runs past its section")
        while e < cend:
            if e + 32 > cend:
                raise ValueError(f"truncated image header at {e:#x}")
            _kind, _unk, ehsz, psz = struct.unpack_from("<HHIQ", data, e)
            arch, = struct.unpack_from("<I", data, e + 28)
            if ehsz < 32 or e + ehsz + psz > cend:
                raise ValueError(f"image at {e:#x} does not fit its container")
            body = e + ehsz
            if arch in keep:
                kept[arch] = kept.get(arch, 0) + psz
            else:
                data[body:body + psz] = bytes(psz)
                zeroed[arch] = zeroed.get(arch, 0) + psz
            e = body + psz
        pos = cend
    if containers == 0:
        raise ValueError("no fatbin container in .nv_fatbin")
    return containers, kept, zeroed


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("lib")
    ap.add_argument("out")
    ap.add_argument("--arch", type=int, action="append", required=True,
                    help="an SM architecture to keep, e.g. 90 for H100/H200 (repeatable)")
    a = ap.parse_args()
    try:
        with open(a.lib, "rb") as f:
            data = bytearray(f.read())
    except OSError as e:
        die(f"cannot read {a.lib}: {e.strerror}")
    try:
        containers, kept, zeroed = prune(data, set(a.arch))
    except (ValueError, struct.error) as e:
        die(f"{a.lib}: {e}")
    if not kept:
        die(f"{a.lib}: no kernels for sm_{'/'.join(map(str, a.arch))} "
            f"(it has {', '.join(f'sm_{k}' for k in sorted(zeroed))})")
    tmp = a.out + ".tmp"
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        os.chmod(tmp, os.stat(a.lib).st_mode & 0o777)
        os.replace(tmp, a.out)
    except OSError as e:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        die(f"cannot write {a.out}: {e.strerror}")
    mb = lambda d: ", ".join(f"sm_{k} {v / 1e6:.1f} MB" for k, v in sorted(d.items()))
    print(f"{a.lib}: {containers} fatbin containers; kept {mb(kept)}; zeroed {mb(zeroed) or 'nothing'}")


if __name__ == "__main__":
    main()
