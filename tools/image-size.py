"""Flash and static RAM of a firmware image, from its section sizes (`llvm-size -A`):
flash = .vector_table + .text + .rodata + .data, static RAM = .data + .bss + .uninit.

    python3 tools/image-size.py ELF [TARGET_JSON]

Prints one JSON line; with TARGET_JSON (`{"flash_bytes": N, "static_ram_bytes": N}`, the real
board's figures CI holds it to) exits 1 when either grows past the checked-in figure, and says
which file to lower when it shrank.
"""
import json
import subprocess
import sys


def sizes(elf):
    out = subprocess.run(["llvm-size", "-A", elf], capture_output=True, text=True,
                         check=True).stdout
    sec = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0].startswith(".") and parts[1].isdigit():
            sec[parts[0]] = int(parts[1])
    flash = sum(sec.get(s, 0) for s in (".vector_table", ".text", ".rodata", ".data"))
    ram = sum(sec.get(s, 0) for s in (".data", ".bss", ".uninit"))
    return {"flash_bytes": flash, "static_ram_bytes": ram}


def main():
    got = sizes(sys.argv[1])
    print(json.dumps(got))
    if len(sys.argv) < 3:
        return 0
    path = sys.argv[2]
    try:
        with open(path) as f:
            want = json.load(f)
    except (OSError, ValueError) as e:
        print(f"image-size: {path}: {e}")
        return 1
    bad = 0
    for key, now in got.items():
        limit = want.get(key)
        if not isinstance(limit, int):
            print(f"image-size: {path}: /{key} missing or not an integer")
            bad = 1
        elif now > limit:
            print(f"image-size: {key} is {now}, above {limit} in {path}")
            bad = 1
        elif now < limit:
            print(f"image-size: {path}: /{key} is now {now}, below {limit}: lower it in the file")
    return bad


if __name__ == "__main__":
    sys.exit(main())
