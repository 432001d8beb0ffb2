"""Does a hand-fused activation pay? ms per training step of sac_continuous.py against two variants.

sac_continuous.py applies its hidden ReLUs in place (kept because of this measurement). `copy`: the ReLUs
return a new tensor instead; `fused`: each critic hidden layer (batched product + in-place ReLU) is one
autograd Function with a hand-written backward (one graph node instead of two). The variants are written from the current sac_continuous.py into
--workdir; each measurement is a fresh process on one torch thread (benchmarks/update_speed.py's
step), the order rotating every repetition.

    python benchmarks/relu_variants.py --widths 256 64 --repeats 5
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
from pathlib import Path

from side_by_side import checked, stop_children_on_sigterm

ROOT = Path(__file__).resolve().parent.parent

FUSED_LAYER = '''

class EnsembleLinearReLU(torch.autograd.Function):
    """relu(baddbmm(b, x, W^T)) as one autograd node, the activation computed in place."""

    @staticmethod
    def forward(ctx, x, weight, bias):
        y = torch.baddbmm(bias, x, weight.transpose(1, 2)).relu_()
        ctx.save_for_backward(x, weight, y)
        return y

    @staticmethod
    def backward(ctx, grad):
        x, weight, y = ctx.saved_tensors
        g = torch.ops.aten.threshold_backward(grad, y, 0)
        grad_x = torch.bmm(g, weight) if ctx.needs_input_grad[0] else None
        grad_w = torch.bmm(g.transpose(1, 2), x) if ctx.needs_input_grad[1] else None
        grad_b = g.sum(1, keepdim=True) if ctx.needs_input_grad[2] else None
        return grad_x, grad_w, grad_b
'''
CRITIC_BODY = """        x = torch.cat([x, a], 1)
        x = F.relu(self.fc1(x), inplace=True)  # in place: the products before need their inputs, not outputs
        x = F.relu(self.fc2(x), inplace=True)
        return self.fc3(x)"""
FUSED_CRITIC_BODY = """        x = torch.cat([x, a], 1).expand(self.fc1.weight.shape[0], -1, -1)
        x = EnsembleLinearReLU.apply(x, self.fc1.weight, self.fc1.bias)
        x = EnsembleLinearReLU.apply(x, self.fc2.weight, self.fc2.bias)
        return self.fc3(x)"""


def write_variants(workdir: Path) -> dict[str, Path]:
    source = (ROOT / "sac_continuous.py").read_text()
    assert CRITIC_BODY in source, "sac_continuous.py's critic changed; update this benchmark"
    copy = source.replace(", inplace=True)", ")")
    fused = source.replace(CRITIC_BODY, FUSED_CRITIC_BODY).replace("\n\nclass SoftQNetwork(", FUSED_LAYER + "\n\nclass SoftQNetwork(")
    paths = {"now": ROOT / "sac_continuous.py", "copy": workdir / "sac_copy.py", "fused": workdir / "sac_fused.py"}
    paths["copy"].write_text(copy)
    paths["fused"].write_text(fused)
    return paths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--widths", type=int, nargs="+", default=[256, 64])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--workdir", type=Path, default=ROOT / "benchmarks" / "results" / "relu_variants")
    args = parser.parse_args()
    minimums = {"--widths": (min(args.widths), 1), "--steps": (args.steps, 1), "--repeats": (args.repeats, 1)}
    if too_small := [f"{flag} must be at least {low}" for flag, (value, low) in minimums.items() if not value >= low]:
        parser.error("; ".join(too_small))
    args.workdir.mkdir(parents=True, exist_ok=True)
    paths = write_variants(args.workdir)
    names = list(paths)
    print("| width | now ms | copy ms | fused ms | copy/now | fused/now |")
    print("|---|---|---|---|---|---|")
    for width in args.widths:
        ms: dict[str, list[float]] = {name: [] for name in names}
        for rep in range(args.repeats):
            for name in names[rep % 3 :] + names[: rep % 3]:
                cmd = [sys.executable, str(ROOT / "benchmarks" / "update_speed.py"), "--worker", "sac", str(paths[name]), str(width), str(args.steps)]
                out = checked(subprocess.run(cmd, capture_output=True, text=True)).stdout
                ms[name].append(float(out.strip().splitlines()[-1]) * 1000.0)

        def ratio(other: str) -> str:
            ratios = [o / n for n, o in zip(ms["now"], ms[other])]
            return f"{statistics.median(ratios):.2f} ({min(ratios):.2f}-{max(ratios):.2f})"

        medians = " | ".join(f"{statistics.median(ms[n]):.2f}" for n in names)
        print(f"| {width} | {medians} | {ratio('copy')} | {ratio('fused')} |", flush=True)


if __name__ == "__main__":
    stop_children_on_sigterm()
    main()
