"""Derive the expected values of mixed_2x4_dropouts.csv WITHOUT using analysis.anova.

Run: /work/main/.venv/bin/python tests/analysis/data/derive_mixed_2x4_dropouts.py
Tools: statsmodels 0.15.0 (type III, OLS model comparison), pingouin 0.7.0 (type II and
sphericity, mixed_anova(correction=True)), scipy 1.17.1.

Type III (as SPSS/afex): complete cases only. Within stratum = OLS on the long data with one dummy
per participant (absorbs the between effect and every participant's level), the within factor in
sum-to-zero (deviation) coding and the within × between product of sum-to-zero codes. The type III
SS of an effect is RSS(model without that effect's columns) − RSS(full model); the error is the
full model's RSS. Between stratum = OLS of participant means on sum-to-zero condition codes,
SS × number of sessions. Generalised η² = SS / (SS + SS_error_between + SS_error_within).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pingouin as pg
import statsmodels.api as sm
from scipy import stats

HERE = Path(__file__).parent


def say(text: str) -> None:
    """Write a line to stdout (this is a script)."""
    sys.stdout.write(text + "\n")


def sum_codes(levels: pd.Series) -> np.ndarray:
    """Deviation coding: level j → e_j for j < k−1, the last level → −1 in every column."""
    cats = sorted(levels.unique())
    k = len(cats)
    codes = np.zeros((len(levels), k - 1))
    for j, cat in enumerate(cats):
        row = -np.ones(k - 1) if j == k - 1 else np.eye(k - 1)[j]
        codes[(levels == cat).to_numpy()] = row
    return codes


def derive(path: Path, dv: str, within: str, between: str, subject: str) -> None:
    df = pd.read_csv(path)
    wide = df.pivot(index=subject, columns=within, values=dv)
    complete = wide.dropna().index
    say(f"excluded: {sorted(set(wide.index) - set(complete))}")
    df = df[df[subject].isin(complete)].reset_index(drop=True)
    n_sessions = df[within].nunique()

    y = df[dv].to_numpy()
    subj = pd.get_dummies(df[subject]).to_numpy(float)
    w = sum_codes(df[within])
    b = sum_codes(df[between])
    wb = np.hstack([w * b[:, [j]] for j in range(b.shape[1])])
    full = sm.OLS(y, np.hstack([subj, w, wb])).fit()
    no_w = sm.OLS(y, np.hstack([subj, wb])).fit()
    no_wb = sm.OLS(y, np.hstack([subj, w])).fit()
    ss_err_w, df_err_w = full.ssr, full.df_resid

    means = df.groupby(subject).agg(m=(dv, "mean"), g=(between, "first")).reset_index()
    b_model = sm.OLS(means["m"].to_numpy(), sm.add_constant(sum_codes(means["g"]))).fit()
    b_null = sm.OLS(means["m"].to_numpy(), np.ones((len(means), 1))).fit()
    ss_b = n_sessions * (b_null.ssr - b_model.ssr)
    ss_err_b, df_err_b = n_sessions * b_model.ssr, b_model.df_resid

    for name, ss, df1, err, df2 in (
        ("between", ss_b, b.shape[1], ss_err_b, df_err_b),
        ("within", no_w.ssr - full.ssr, w.shape[1], ss_err_w, df_err_w),
        ("interaction", no_wb.ssr - full.ssr, wb.shape[1], ss_err_w, df_err_w),
    ):
        f = (ss / df1) / (err / df2)
        say(
            f"type III {name}: F={f!r} df=({df1}, {df2}) p={stats.f.sf(f, df1, df2)!r} "
            f"np2={ss / (ss + err)!r} ng2={ss / (ss + ss_err_b + ss_err_w)!r}"
        )
    aov = pg.mixed_anova(
        data=df, dv=dv, within=within, between=between, subject=subject, correction=True
    )
    ng2 = pg.mixed_anova(
        data=df, dv=dv, within=within, between=between, subject=subject, effsize="ng2"
    )["ng2"]
    with pd.option_context("display.precision", 12, "display.width", 200):
        say("pingouin type II:")
        say(str(aov.assign(ng2=ng2).T))


if __name__ == "__main__":
    derive(HERE / "mixed_2x4_dropouts.csv", "trust", "session", "condition", "participant")
