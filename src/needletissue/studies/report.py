"""Study outputs: tables (Parquet, CSV), summary, figures and the run files, all written atomically."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from needletissue.runinfo import write_atomic, write_run_files
from needletissue.studies import analysis
from needletissue.studies.models import get_model


CSV_MAX_ROWS = 200_000


def write_outputs(cfg, res, params: list[str]) -> None:
    out = res.out_dir
    model = get_model(cfg.study.model)
    outputs = list(model.outputs)
    df = res.results.drop(columns=["run_id", "chunk_wall_time_s", "chunk_start_unix", "chunk_end_unix",
                                    "chunk_worker"], errors="ignore")
    buf = io.BytesIO()
    df.to_parquet(buf, index=False)
    write_atomic(out / "results.parquet", buf.getvalue())
    # CSV is for people and spreadsheets; past CSV_MAX_ROWS it is hundreds of MB: Parquet only.
    csv = len(df) <= CSV_MAX_ROWS
    if csv:
        write_atomic(out / "results.csv", df.to_csv(index=False))
    write_atomic(out / "failures.csv", df[df["status"] != "ok"].to_csv(index=False))

    summary = {"statistics": analysis.statistics(df, outputs)}
    if len(df) > 2:
        summary["sensitivity_src"] = analysis.src(df, params, outputs)
    if cfg.study.method == "sobol":
        summary["sensitivity_sobol"] = analysis.sobol(df, params, outputs, cfg.study.seed)
    res.summary = summary
    plotted = list(cfg.study.outputs or model.primary_outputs or outputs)
    res.figures = figures(cfg, df, params, plotted, summary, out / "figures")

    results = {
        "study": cfg.study.name, "model": cfg.study.model, "method": cfg.study.method,
        "n_cases": res.n_cases, "n_ok": res.n_ok, "n_failed": res.n_failed,
        "computed_this_run": res.computed_this_run, "resumed": res.resumed, "timing": res.timing,
        "failures": res.failures[:1000], "summary": summary,
        "files": {"results": ["results.parquet", *(["results.csv"] if csv else [])], "failures": "failures.csv",
                  "figures": [str(p.relative_to(out)) for p in res.figures]},
    }
    # results.json last: its presence marks a finished study.
    write_run_files(out, cfg.model_dump(mode="json"), results)


def figures(cfg, df, params, outputs, summary, fig_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig_dir.mkdir(parents=True, exist_ok=True)
    ok = df[df["status"] == "ok"]
    paths = []
    # Cap scatter points: a million dots says no more than 20,000 and costs minutes.
    sc = ok.sample(n=min(len(ok), 20_000), random_state=0) if len(ok) else ok
    for o in outputs:
        y = ok[o].to_numpy(float)
        y = y[np.isfinite(y)]
        if y.size == 0:
            continue
        fig, ax = plt.subplots(figsize=(5, 3.5))
        ax.hist(y, bins=min(60, max(10, int(np.sqrt(y.size)))), color="tab:blue", alpha=0.8)
        st = summary["statistics"][o]
        for key, ls in (("p2.5", ":"), ("p50", "-"), ("p97.5", ":")):
            ax.axvline(st[key], color="k", ls=ls, lw=1)
        ax.set_xlabel(o)
        ax.set_ylabel("cases")
        ax.set_title(f"{cfg.study.name}: {o}\nmean {st['mean']:.3g}, std {st['std']:.3g} (n = {st['n']:,})",
                     fontsize=9)
        paths.append(_save(fig, fig_dir / f"hist_{o}.png"))

        fig, axes = plt.subplots(1, len(params), figsize=(3.2 * len(params), 3), squeeze=False)
        for ax, p in zip(axes[0], params):
            ax.scatter(sc[p], sc[o], s=2, alpha=0.3)
            ax.set_xlabel(p)
        axes[0][0].set_ylabel(o)
        paths.append(_save(fig, fig_dir / f"scatter_{o}.png"))

        sens = summary.get("sensitivity_sobol", {}).get(o) or summary.get("sensitivity_src", {}).get(o)
        if sens and (sens.get("indices") or sens.get("first_order")):
            fig, ax = plt.subplots(figsize=(5, 3))
            x = np.arange(len(params))
            if "first_order" in sens:
                ax.bar(x - 0.2, [sens["first_order"][p] for p in params], 0.4, label="first order S1")
                ax.bar(x + 0.2, [sens["total"][p] for p in params], 0.4, label="total ST")
                ax.set_ylabel("Sobol index")
                ax.legend(fontsize=8)
            else:
                ax.bar(x, [sens["indices"][p] for p in params])
                r2 = sens.get("r2")
                ax.set_ylabel("SRC" + (f" (R$^2$ = {r2:.3f})" if r2 is not None else ""))
            ax.axhline(0, color="k", lw=0.5)
            ax.set_xticks(x, params, rotation=30, ha="right", fontsize=8)
            ax.set_title(f"Sensitivity of {o}", fontsize=9)
            paths.append(_save(fig, fig_dir / f"sensitivity_{o}.png"))
    return paths


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return write_atomic(path, buf.getvalue())
