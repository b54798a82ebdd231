"""Counts the instructions of a QEMU exec trace inside Drive::control (see tick-profile.sh)."""
import bisect
import collections
import re
import subprocess
import sys

from inline_chains import inline_chains


def symbols(elf):
    out = subprocess.run(["llvm-nm", "-C", "-S", elf], capture_output=True, text=True, check=True)
    syms = []
    for line in out.stdout.splitlines():
        parts = line.split(None, 3)
        if len(parts) == 4 and parts[2] in "tT":
            start = int(parts[0], 16) & ~1
            syms.append((start, start + int(parts[1], 16), parts[3]))
    syms.sort()
    return syms


def main(elf, trace, top=40, over=500):
    syms = symbols(elf)
    starts = [s[0] for s in syms]
    step = next(s for s in syms if "Drive::control" in s[2])
    caller = next(s for s in syms if s[2] == "TIM7")
    pc_re = re.compile(r"\[[0-9a-f]+/([0-9a-f]+)/")
    counts, ticks, inside = collections.Counter(), 0, False
    # The heaviest tick's own instructions: where the per-tick maximum goes.
    this, heaviest = collections.Counter(), collections.Counter()
    # Every tick over the budget's maximum: which parts make it heavy.
    heavy_ticks = []
    # Every tick's own instructions: each function's heaviest tick.
    all_ticks = []
    with open(trace, errors="replace") as f:
        for line in f:
            m = pc_re.search(line)
            if not m:
                continue
            pc = int(m.group(1), 16)
            if pc == step[0]:
                inside, ticks = True, ticks + 1
                this = collections.Counter()
            elif inside and caller[0] <= pc < caller[1]:
                inside = False
                all_ticks.append(this)
                total = sum(this.values())
                if total > sum(heaviest.values()):
                    heaviest = this
                if total > over:
                    heavy_ticks.append((ticks, this))
            if inside:
                counts[pc] += 1
                this[pc] += 1
    if ticks == 0:
        sys.exit("tick-profile: no Drive::control call in the trace")
    print(f"\n{ticks} ticks, {sum(counts.values()) / ticks:.1f} instructions per tick in Drive::control")

    def name(pc):
        i = bisect.bisect_right(starts, pc) - 1
        return syms[i][2] if i >= 0 and syms[i][0] <= pc < syms[i][1] else "?"

    fn_of = {pc: re.sub(r"::h[0-9a-f]{16}$", "", name(pc)) for pc in counts}
    by_fn, fn_max = collections.Counter(), collections.Counter()
    for pc, n in counts.items():
        by_fn[fn_of[pc]] += n
    for tick in all_ticks:
        per_fn = collections.Counter()
        for pc, n in tick.items():
            per_fn[fn_of[pc]] += n
        for fn, n in per_fn.items():
            fn_max[fn] = max(fn_max[fn], n)
    print("\nper function (after inlining), mean and heaviest tick:")
    for fn, n in by_fn.most_common(top):
        print(f"{n / ticks:8.1f} {fn_max[fn]:6d}  {fn}")
    # The model's own: every function of `estimator_core::model` but the dispatch, summed per
    # tick (Model 4's `operator::eval` calls `BeltState::advance` out of line).
    def is_own(fn):
        return fn.startswith("estimator_core::model::") and not re.match(
            r"estimator_core::model::estimate(_with_current)?$", fn)
    own = [sum(n for pc, n in tick.items() if is_own(fn_of[pc])) for tick in all_ticks]
    if own:
        print(f"\nthe model's own (estimator_core::model but the dispatch): "
              f"{sum(own) / len(own):.1f} mean, {max(own)} heaviest tick")

    pcs = sorted(counts)
    chains = inline_chains(elf, pcs)
    by_line, where_of = collections.Counter(), {}
    for pc in pcs:
        own = [c for c in chains.get(pc, []) if "/estimator-core/" in c or "/belt-link/" in c]
        where = own[0] if own else (chains.get(pc) or ["?"])[0]
        where_of[pc] = re.sub(r".*/(estimator-core|belt-link)/", r"\1/", where).split(" ")[0]
        by_line[where_of[pc]] += counts[pc]
    by_file = collections.Counter()
    for where, n in by_line.items():
        by_file[where.split(":")[0]] += n
    print("\nper source file (innermost file of this workspace):")
    for where, n in by_file.most_common(top):
        print(f"{n / ticks:8.1f}  {where}")
    print("\nper source line (innermost line of this workspace):")
    for where, n in by_line.most_common(top):
        print(f"{n / ticks:8.1f}  {where}")
    heavy_file, heavy_line = collections.Counter(), collections.Counter()
    for pc, n in heaviest.items():
        heavy_file[where_of[pc].split(":")[0]] += n
        heavy_line[where_of[pc]] += n
    print(f"\nthe heaviest tick ({sum(heaviest.values())} instructions in Drive::control), per source file:")
    for where, n in heavy_file.most_common(top):
        print(f"{n:8d}  {where}")
    print("\nthe heaviest tick, per source line:")
    for where, n in heavy_line.most_common(top // 2):
        print(f"{n:8d}  {where}")
    print(f"\n{len(heavy_ticks)} ticks over {over} instructions (tick number, total, largest files):")
    for k, tick in heavy_ticks[:top]:
        files = collections.Counter()
        for pc, n in tick.items():
            files[where_of.get(pc, "?").split(":")[0].split("/")[-1]] += n
        parts = ", ".join(f"{f} {n}" for f, n in files.most_common(5))
        print(f"{k:8d} {sum(tick.values()):5d}  {parts}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else 40, int(sys.argv[4]) if len(sys.argv) > 4 else 500)
