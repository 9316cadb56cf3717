"""The paper appendix's cross re-enactment table for our avatars (issue #30): rows = transfer modes, columns = dlib
identity similarity, FER2013 expression similarity and landmark agreement, per (avatar, driver) pair and averaged;
self re-enactment (the avatar's own test frames) beside them. Quality numbers only: it runs on a loaded machine.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/cross_reenactment.py --out bench_out/cross \\
        --avatar duda=/work/exp/runs/duda --avatar wojtek=/work/exp/runs/wojtek \\
        --driver duda=/work/exp/d/duda/dataset --driver wojtek=/work/exp/d/wojtek/dataset \\
        --synth-subject 1 --max-frames 100 --stills docs/images

Each avatar is driven by every --driver except its own (and by a generated subject, `geoavatar synth --subject N`,
written once to OUT/synth<N>), in every transfer mode, through apps/reenact.py's DrivenAvatar and apps/eval.py's
evaluate_cross (what `geoavatar eval RUN --driver D --transfer ...` runs; each pair's report, as eval writes it to
RUN/eval/cross@<driver>/, goes to OUT/reports/<avatar>_by_<driver>/ here, so that the runs are left as they were).
Self re-enactment: eval's test split with the face metrics. Writes OUT/table.md and OUT/table.json (each mode
minus relative frame by frame beside the means), and picks the default mode by the rule of #30: the best
expression similarity among the modes that beat relative on it without losing more than 0.01 identity similarity
(averaged over the pairs); with --stills DIR, PNGs of driver | relative | that mode (or the best other mode when
relative stays) at the three frames of each pair where the two renders differ most.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from geoavatar.apps.common import side_by_side
from geoavatar.apps.eval import evaluate_cross
from geoavatar.apps.expression_transfer import TRANSFER_MODES
from geoavatar.apps.reenact import DrivenAvatar, DrivingOptions, driver_picture
from geoavatar.data import evenly_spaced
from geoavatar.eval.cross import write_cross_report
from geoavatar.eval.evaluate import EvalConfig, evaluate_run, face_scorer
from geoavatar.imaging import fit_height, to_uint8
from geoavatar.io.atomic import atomic_write_json, atomic_write_png, atomic_write_text
from geoavatar.train.checkpoint import load_run

COLUMNS = (("id_similarity", "ID"), ("expression_similarity", "Expr"), ("landmark_agreement", "LM"))
ID_LOSS = 0.01  # #30: the default may lose at most this much identity similarity to relative transfer


def value(summary: dict, key: str) -> float | None:
    return summary["landmark_agreement"]["agreement"] if key == "landmark_agreement" else summary[key]["mean"]


def synth_driver(out: Path, subject: int, frames: int, size: int) -> Path:
    from geoavatar.data.synth.generate import SynthConfig, generate_dataset

    folder = out / f"synth{subject}"
    if not (folder / "transforms.json").is_file():
        generate_dataset(folder, SynthConfig(subject=subject, frames=frames, size=size), progress=False)
    return folder


def self_row(run, max_frames: int | None) -> dict:
    result = evaluate_run(run, EvalConfig(max_frames=max_frames, floaters=False, mouth=False), progress=False)
    return {"id_similarity": result.summary["id_similarity"]["mean"],
            "expression_similarity": result.summary["expression_similarity"]["mean"],
            "landmark_agreement": result.faces["landmark_agreement"]["agreement"],
            "faces": result.faces["faces"], "psnr": result.summary["psnr"]["mean"]}


def mean(values) -> float | None:
    kept = [v for v in values if v is not None]
    return float(np.mean(kept)) if kept else None


def pick_default(pairs: dict) -> tuple[str, dict]:
    """(the chosen mode, the per-mode means over the pairs) by #30's rule; relative when no mode qualifies."""
    means = {mode: {key: mean(value(p["summary"][mode], key) for p in pairs.values()) for key, _ in COLUMNS}
             for mode in TRANSFER_MODES}
    base = means["relative"]
    qualified = [m for m in TRANSFER_MODES if m != "relative"
                 and means[m]["expression_similarity"] > base["expression_similarity"]
                 and means[m]["id_similarity"] >= base["id_similarity"] - ID_LOSS]
    chosen = max(qualified, key=lambda m: means[m]["expression_similarity"]) if qualified else "relative"
    return chosen, means


def paired(result, mode: str, key: str, base: str = "relative") -> list[float] | None:
    """[mean, standard error, frames] of `key` in `mode` minus `base`, over the frames both scored (None: < 2)."""
    pairs = [(getattr(a, key), getattr(b, key)) for (_, a), (_, b) in zip(result.modes[mode], result.modes[base])]
    deltas = np.array([a - b for a, b in pairs if a is not None and b is not None])
    if len(deltas) < 2:
        return None
    return [float(deltas.mean()), float(deltas.std(ddof=1) / np.sqrt(len(deltas))), int(len(deltas))]


def difference_table(pairs: dict) -> str:
    """Each mode minus relative, frame by frame (mean ± standard error over the frames both scored)."""
    names = list(pairs)
    lines = ["| Transfer | " + " | ".join(f"{n} ΔID | {n} ΔExpr" for n in names) + " |",
             "|---|" + "---:|" * (2 * len(names))]
    for mode in TRANSFER_MODES:
        if mode == "relative":
            continue
        cells = []
        for n in names:
            for key in ("id_similarity", "expression_similarity"):
                d = pairs[n]["paired"][mode][key]
                cells.append("–" if d is None else f"{d[0]:+.3f} ± {d[1]:.3f}")
        lines.append(f"| {mode} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def cell(number: float | None) -> str:
    return "–" if number is None else f"{number:.3f}"


def table(pairs: dict, selfs: dict, means: dict) -> str:
    names = list(pairs)
    head = ("| Transfer | " + " | ".join(f"{n} {c}" for n in names for _, c in COLUMNS)
            + " | mean ID | mean Expr | mean LM |")
    lines = [head, "|---|" + "---:|" * (3 * len(names) + 3)]
    for mode in TRANSFER_MODES:
        cells = [cell(value(pairs[n]["summary"][mode], key)) for n in names for key, _ in COLUMNS]
        cells += [cell(means[mode][key]) for key, _ in COLUMNS]
        lines.append(f"| {mode} | " + " | ".join(cells) + " |")
    cells = [cell(selfs[pairs[n]["avatar"]][key]) for n in names for key, _ in COLUMNS]
    cells += [cell(mean(s[key] for s in selfs.values())) for key, _ in COLUMNS]
    lines.append("| self (test split) | " + " | ".join(cells) + " |")
    drivers = [cell(pairs[n]["summary"]["relative"]["source_id_similarity"]["mean"]) for n in names]
    lines.append("| the driver's own face | " + " | ".join(f"{d} | – | –" for d in drivers) + " | | | |")
    return "\n".join(lines) + "\n"


@torch.no_grad()
def stills(run, driven: DrivenAvatar, modes: tuple[str, str], path: Path, frames: int, rows: int = 3,
           height: int = 128) -> list[int]:
    """driver | modes[0] | modes[1] at the `rows` driver frames (of `frames` spread evenly) where they differ most."""
    scored = []
    for index in evenly_spaced(len(driven.dataset), frames):
        item = driven.dataset[index]
        a, b = (driven.render(item, mode) for mode in modes)
        scored.append((float((a - b).abs().mean()), index))
    chosen = sorted(index for _, index in sorted(scored, reverse=True)[:rows])
    picture = []
    for index in chosen:
        item = driven.dataset[index]
        panels = [driver_picture(item), *(driven.render(item, mode) for mode in modes)]
        picture.append(side_by_side(*(fit_height(to_uint8(p), height) for p in panels)))
    image = Image.fromarray(np.concatenate(picture, 0)).quantize(colors=128, method=Image.Quantize.MEDIANCUT)
    atomic_write_png(path, image, optimize=True)  # 128 colours: small enough for docs/images
    return [int(driven.dataset[i]["timestep"]) for i in chosen]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--avatar", action="append", required=True, help="NAME=RUN")
    parser.add_argument("--driver", action="append", default=[], help="NAME=DATASET (an avatar's own is skipped)")
    parser.add_argument("--synth-subject", type=int, default=1)
    parser.add_argument("--synth-frames", type=int, default=200)
    parser.add_argument("--synth-size", type=int, default=512)
    parser.add_argument("--max-frames", type=int, default=100, help="driver frames per pair, spread evenly")
    parser.add_argument("--self-frames", type=int, default=None, help="test frames of self re-enactment (all)")
    parser.add_argument("--stills", type=Path, default=None, help="folder for the stills PNGs")
    args = parser.parse_args()
    torch.set_num_threads(1)
    avatars = dict(item.split("=", 1) for item in args.avatar)
    drivers = {name: Path(path) for name, path in (item.split("=", 1) for item in args.driver)}
    drivers[f"synth{args.synth_subject}"] = synth_driver(args.out, args.synth_subject, args.synth_frames,
                                                         args.synth_size)
    pairs, selfs, driven_of = {}, {}, {}
    for avatar, run_dir in avatars.items():
        run = load_run(run_dir)
        selfs[avatar] = self_row(run, args.self_frames)
        print(f"{avatar} self: {selfs[avatar]}", flush=True)
        with face_scorer(run) as scorer:  # the avatar's identity reference, read once for its drivers
            for driver, root in drivers.items():
                if driver == avatar:
                    continue
                driven = DrivenAvatar(run, root, DrivingOptions())
                result = evaluate_cross(run, driven, TRANSFER_MODES, driver, args.max_frames, scorer=scorer,
                                        progress=False)
                write_cross_report(result, args.out / "reports" / f"{avatar}_by_{driver}")
                name = f"{avatar}←{driver}"
                pairs[name] = {"avatar": avatar, "driver": driver, "summary": result.summaries,
                               "paired": {mode: {key: paired(result, mode, key)
                                                 for key in ("id_similarity", "expression_similarity")}
                                          for mode in TRANSFER_MODES if mode != "relative"}}
                driven_of[name] = (run, driven)
                print(f"{name}: " + json.dumps({m: [cell(value(s, k)) for k, _ in COLUMNS]
                                                for m, s in result.summaries.items()}), flush=True)
    chosen, means = pick_default(pairs)
    markdown = (table(pairs, selfs, means)
                + "\nEach mode minus relative, frame by frame (mean ± standard error over the frames both renders "
                  "showed a face in; frames of a clip are correlated, so the errors are optimistic):\n\n"
                + difference_table(pairs) + "\nDefault by #30's rule (best expression among the modes beating "
                f"relative on it within {ID_LOSS} identity): **{chosen}**\n")
    record = {"pairs": pairs, "self": selfs, "means": means, "default": chosen, "max_frames": args.max_frames}
    if args.stills is not None:  # relative against the default, or against the best other mode when relative stays
        shown = chosen if chosen != "relative" else max((m for m in TRANSFER_MODES if m != "relative"),
                                                        key=lambda m: means[m]["expression_similarity"] or -1.0)
        record["stills"] = {"modes": ["relative", shown]}
        for name, (run, driven) in driven_of.items():
            path = args.stills / f"cross_{pairs[name]['avatar']}_by_{pairs[name]['driver']}.png"
            record["stills"][name] = {"png": str(path), "timesteps": stills(run, driven, ("relative", shown), path,
                                                                             args.max_frames)}
    atomic_write_text(args.out / "table.md", markdown)
    atomic_write_json(args.out / "table.json", record)
    print(markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
