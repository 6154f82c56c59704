# Reference values of the linear mixed models in test_lmm_lmertest.py, at full precision.
# Run from this folder: Rscript lmm_lmertest.R   (writes lmm_lmertest.json)
# R 4.2.2, lme4 1.1.31, lmerTest 3.1.3, jsonlite (Debian packages).
# For each CSV (participant, condition, session, trust; rows with a missing trust dropped) and
# each model, as trustlab's linear_mixed_models fits them (contr.sum, REML):
#   intercept: trust ~ condition * session_f + (1 | participant)
#   slope:     trust ~ condition * session_f + (1 + step | participant), step = session - 1
# once with lme4's default optimiser settings ("default") and once with nloptwrap's tolerances
# tightened to the precision of the REML optimum itself ("tight"). It stores summary(m)'s
# coefficients (Satterthwaite), anova(m, type = 3), the variance components (SDs, correlation),
# logLik, theta, isSingular, lme4's convergence messages and the estimated marginal mean of every
# condition × session cell (lmerTest::contest of the cell's model-matrix row).
suppressMessages(library(lmerTest))
options(contrasts = c("contr.sum", "contr.poly"))
cases <- c("lmm_boundary_intercept", "lmm_boundary_slope", "lmm_flat_intercept",
           "mixed_2x4_dropouts", "lmm_synthetic_100")
out <- list()
for (case in cases) {
  d <- read.csv(paste0(case, ".csv"))
  d <- d[!is.na(d$trust), ]
  d$condition <- factor(d$condition)
  d$session_f <- factor(d$session)
  d$step <- as.integer(d$session_f) - 1
  models <- list(
    intercept = trust ~ condition * session_f + (1 | participant),
    slope = trust ~ condition * session_f + (1 + step | participant)
  )
  for (name in names(models)) for (optimum in c("default", "tight")) {
    control <- if (optimum == "default") lmerControl() else lmerControl(
      optimizer = "nloptwrap",
      optCtrl = list(ftol_abs = 1e-15, xtol_abs = 1e-12, ftol_rel = 1e-15, xtol_rel = 1e-12)
    )
    m <- lmer(models[[name]], data = d, REML = TRUE, control = control)
    coefs <- summary(m)$coefficients
    tests <- anova(m, type = 3)
    vc <- as.data.frame(VarCorr(m))
    grid <- expand.grid(session_f = levels(d$session_f), condition = levels(d$condition))
    grid$session_f <- factor(grid$session_f, levels = levels(d$session_f))
    grid$condition <- factor(grid$condition, levels = levels(d$condition))
    cells <- model.matrix(~ condition * session_f, grid)
    emm <- contest(m, cells, joint = FALSE)
    out[[paste(case, name, optimum)]] <- list(
      case = case, model = name, optimizer = optimum,
      converged = is.null(m@optinfo$conv$lme4$messages) ||
        all(grepl("singular", m@optinfo$conv$lme4$messages)),
      messages = paste(m@optinfo$conv$lme4$messages, collapse = "; "),
      singular = isSingular(m),
      loglik = as.numeric(logLik(m)),
      theta = unname(getME(m, "theta")),
      sd = vc$sdcor[is.na(vc$var2)],
      corr = if (name == "slope") vc$sdcor[!is.na(vc$var2)] else NULL,
      fixed = list(term = rownames(coefs), estimate = unname(coefs[, "Estimate"]),
                   se = unname(coefs[, "Std. Error"]), df = unname(coefs[, "df"]),
                   t = unname(coefs[, "t value"]), p = unname(coefs[, "Pr(>|t|)"])),
      tests = list(effect = rownames(tests), F = tests[["F value"]], df1 = tests$NumDF,
                   df2 = tests$DenDF, p = tests[["Pr(>F)"]]),
      emmeans = list(condition = as.character(grid$condition),
                     session = as.character(grid$session_f),
                     emmean = emm$Estimate, se = emm[["Std. Error"]], df = emm$df)
    )
  }
}
jsonlite::write_json(unname(out), "lmm_lmertest.json", digits = NA, auto_unbox = TRUE,
                     pretty = TRUE)
