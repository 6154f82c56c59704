# Reference values of the boundary (singular) linear mixed models in test_lmm.py.
# Run from this folder: Rscript lmm_boundary.R
# Computed with R 4.2.2, lme4 1.1.31, lmerTest 3.1.3 (Debian packages).
suppressMessages(library(lmerTest))
options(contrasts = c("contr.sum", "contr.poly"), digits = 10)
for (case in c("lmm_boundary_intercept", "lmm_boundary_slope", "lmm_flat_intercept")) {
  d <- read.csv(paste0(case, ".csv"))
  d$condition <- factor(d$condition)
  d$session_f <- factor(d$session)
  d$step <- d$session - 1
  models <- list(
    intercept = trust ~ condition * session_f + (1 | participant),
    slope = trust ~ condition * session_f + (1 + step | participant)
  )
  for (name in names(models)) {
    m <- lmer(models[[name]], data = d, REML = TRUE)
    cat("\n====", case, name, "====\n")
    cat("isSingular:", isSingular(m), " REML logLik:", format(as.numeric(logLik(m)), digits = 10), "\n")
    cat("theta:", format(getME(m, "theta"), digits = 10), "\n")
    print(as.data.frame(VarCorr(m)), digits = 10)
    print(as.data.frame(anova(m, type = 3))[, c("F value", "NumDF", "DenDF", "Pr(>F)")], digits = 10)
  }
}
