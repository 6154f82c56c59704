# lme4/lmerTest side of `bench/analysis.py --vs-r` (issue 49): the study's linear mixed models of
# one CSV (participant, condition, session, trust), as trustlab's linear_mixed_models fits them.
#   Rscript bench/lmer.R CSV MODELS REPEATS
# MODELS is "intercept" (trust ~ condition * session_f + (1 | participant)) or "slope" (that
# model and trust ~ condition * session_f + (1 + step | participant), as `trustlab mixed
# --random-slope`). Each model: lmer (REML), anova(type = 3) (Satterthwaite), summary.
# REPEATS = 0: fit once and print the type III table (the command-line comparison, start-up
# included). REPEATS > 0: a warm-up fit, then REPEATS fits timed in-process with system.time;
# prints one JSON line with the elapsed seconds and the numbers of a last, untimed fit with
# nloptwrap's tolerances tightened (lme4's defaults stop up to ~1e-4 short of the REML optimum
# on flat likelihoods; tests/analysis/data/lmm_lmertest.R).
suppressMessages(library(lmerTest))
options(contrasts = c("contr.sum", "contr.poly"))
args <- commandArgs(trailingOnly = TRUE)
d <- read.csv(args[1])
d <- d[!is.na(d$trust), ]
d$condition <- factor(d$condition)
d$session_f <- factor(d$session)
d$step <- as.integer(d$session_f) - 1
formulas <- list(intercept = trust ~ condition * session_f + (1 | participant))
if (args[2] == "slope") {
  formulas$slope <- trust ~ condition * session_f + (1 + step | participant)
}
repeats <- as.integer(args[3])
tight <- lmerControl(
  optimizer = "nloptwrap",
  optCtrl = list(ftol_abs = 1e-15, xtol_abs = 1e-12, ftol_rel = 1e-15, xtol_rel = 1e-12)
)
fit_all <- function(control = lmerControl()) {
  lapply(formulas, function(f) {
    m <- suppressMessages(suppressWarnings(lmer(f, data = d, REML = TRUE, control = control)))
    list(model = m, tests = anova(m, type = 3), summary = summary(m))
  })
}
if (repeats == 0) {
  fits <- fit_all()
  for (name in names(fits)) print(fits[[name]]$tests)
} else {
  fits <- fit_all()  # warm-up
  seconds <- replicate(repeats, system.time(fits <- fit_all())[["elapsed"]])
  values <- lapply(fit_all(tight), function(fit) {
    coefs <- fit$summary$coefficients
    list(loglik = as.numeric(logLik(fit$model)),
         estimate = unname(coefs[, "Estimate"]), se = unname(coefs[, "Std. Error"]),
         df = unname(coefs[, "df"]), F = fit$tests[["F value"]], df2 = fit$tests$DenDF,
         p = fit$tests[["Pr(>F)"]])
  })
  cat(jsonlite::toJSON(list(seconds = seconds, values = values), digits = NA,
                       auto_unbox = TRUE), "\n")
}
