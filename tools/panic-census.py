"""Panic census of a firmware image: every call into a panic entry point, by entry point and by
the innermost source file of this workspace it was inlined from (or "(dependency)").

    python3 tools/panic-census.py ELF [ALLOWED]

Prints the census; with ALLOWED (lines `COUNT ENTRY FILE`, `#` comments), exits 1 when a site
is not allowed there or more sites than allowed are found, so a new panic path fails CI where
it appears. Needs llvm-objdump and addr2line.
"""
import collections
import re
import subprocess
import sys

from inline_chains import inline_chains

# What a panic enters through. `panic_fmt` counts too (an `assert!` with a message, e.g. the
# order check of `Ord::clamp`, calls it directly), except from inside the other entries.
ENTRIES = re.compile(
    r"<(core::panicking::panic(?:_const::\w+|_bounds_check|_nounwind|_fmt)?|"
    r"core::slice::index::\w+|core::option::\w+|core::result::\w+|_defmt_panic)>"
)


def census(elf):
    dis = subprocess.run(["llvm-objdump", "-d", "--no-show-raw-insn", "-C", elf],
                         capture_output=True, text=True, check=True).stdout
    calls = []
    inside_entry = False
    for line in dis.splitlines():
        f = re.match(r"^[0-9a-f]+ <(.*)>:", line)
        if f:
            inside_entry = bool(ENTRIES.fullmatch("<" + f.group(1) + ">"))
            continue
        m = re.match(r"\s+([0-9a-f]+):\s+(bl|b\.w|b)\s", line)
        if m:
            e = ENTRIES.search(line)
            if e and "+0x" not in line.split("<", 1)[1]:
                if e.group(1) == "core::panicking::panic_fmt" and inside_entry:
                    continue
                calls.append((int(m.group(1), 16), e.group(1)))
    chains = inline_chains(elf, [a for a, _ in calls])
    sites = collections.Counter()
    for addr, entry in calls:
        own = [c for c in chains.get(addr, []) if "/registry/" not in c and "/rustc/" not in c
               and not c.startswith("??")]
        where = own[0].split(":")[0] if own else "(dependency)"
        # Workspace-relative, whatever the clone's path.
        where = re.sub(r".*?/((src|estimator-core|belt-link)/)", r"\1", where)
        sites[(entry, where)] += 1
    return sites


def main():
    elf = sys.argv[1]
    sites = census(elf)
    print(f"panic census of {elf}: {sum(sites.values())} call sites")
    for (entry, where), n in sorted(sites.items(), key=lambda kv: kv[0][1]):
        print(f"{n:4d}  {entry:55s} {where}")
    if len(sys.argv) < 3:
        return 0
    allowed = collections.Counter()
    with open(sys.argv[2]) as f:
        for line in f:
            line = line.split("#", 1)[0].strip()
            if line:
                n, entry, where = line.split(None, 2)
                allowed[(entry, where)] = int(n)
    bad = [(k, n) for k, n in sites.items() if n > allowed[k]]
    for (entry, where), n in bad:
        print(f"panic-census: {n} call(s) of {entry} from {where}, {allowed[(entry, where)]} "
              f"allowed by {sys.argv[2]}: remove the panic path (or argue it there)")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
