"""The inline chain of source locations of each address of an ELF (`addr2line -i`), innermost
first: shared by tick-profile.py and panic-census.py."""
import subprocess


def inline_chains(elf, addrs):
    """{address: ["file:line ...", ...]} for every address in `addrs`, innermost first."""
    if not addrs:
        return {}
    out = subprocess.run(["addr2line", "-e", elf, "-i", "-a"] + [hex(a) for a in addrs],
                         capture_output=True, text=True, check=True).stdout.splitlines()
    chains, cur = {}, None
    for line in out:
        if line.startswith("0x"):
            cur = int(line, 16)
            chains[cur] = []
        elif cur is not None:
            chains[cur].append(line)
    return chains
