"""What every flight report writes the same way (``gsoe sim``, ``gsoe replay``): ``metrics.json`` and the pieces of
``report.html`` (a metrics table, captioned figures).  Each report draws its own figures; they are written and
listed here (:class:`SavedFigures`)."""

from __future__ import annotations

import html
import json
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

METRICS_FILE = "metrics.json"
REPORT_FILE = "report.html"
#: resolution of every report figure (PNG)
PLOT_DPI = 90
# Shared style of the report pages.
PAGE_CSS = "body{font-family:sans-serif;max-width:1000px;margin:auto}td{padding:2px 8px}img{max-width:100%}"


def _json_default(o: Any) -> Any:
    if isinstance(o, np.integer | np.floating):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def write_metrics(out_dir: str | Path, metrics: Mapping[str, Any]) -> Path:
    """``out_dir/metrics.json``, written atomically; a non-finite top-level float becomes ``null``."""
    p = Path(out_dir) / METRICS_FILE
    tmp = p.with_suffix(".json.tmp")
    clean = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in metrics.items()}
    tmp.write_text(json.dumps(clean, indent=2, sort_keys=True, default=_json_default))
    tmp.replace(p)
    return p


def fmt_value(v: Any) -> str:
    """A metric as shown in a report table: floats to 4 significant digits, ``nan`` for a non-finite one."""
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.4g}"
    return str(v)


def metrics_rows_html(metrics: Mapping[str, Any], skip: Iterable[str] = ()) -> str:
    """The ``<tr>`` rows of a metrics table, sorted by name, without the keys in ``skip``."""
    left_out = set(skip)
    return "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(fmt_value(v))}</td></tr>"
                   for k, v in sorted(metrics.items()) if k not in left_out)


def figures_html(figs: Iterable[tuple[str, str]]) -> str:
    """``<figure>`` elements for ``(file name, caption)`` pairs (images beside the page)."""
    return "".join(f'<figure><img src="{n}" alt="{html.escape(c)}"><figcaption>{html.escape(c)}</figcaption>'
                   f"</figure>" for n, c in figs)


class SavedFigures:
    """The captioned PNG figures of one report, written into ``out_dir`` as they are drawn.

    Makes matplotlib draw off-screen (Agg) and gives its pyplot as :attr:`plt`; :attr:`figs` lists
    ``(file name, caption)`` for :func:`figures_html`."""

    def __init__(self, out_dir: str | Path) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        self.plt = plt
        self.out_dir = Path(out_dir)
        self.figs: list[tuple[str, str]] = []

    def save(self, fig: Any, name: str, caption: str) -> None:
        """Lay ``fig`` out, write it as ``out_dir/name``, close it (pyplot keeps every open figure) and list it."""
        fig.tight_layout()
        fig.savefig(self.out_dir / name, dpi=PLOT_DPI)
        self.plt.close(fig)
        self.figs.append((name, caption))
