# lmerTest 3.1.3, lme4 1.1.31, emmeans 1.8.4.1 (Debian r-cran-lmertest, r-cran-emmeans) on the covariate test data:
# the reference values hard-coded in tests/analysis/test_lmm_covariates.py. Run from the repository root.
suppressMessages({library(lmerTest)})
d <- read.csv("tests/analysis/data/lmm_language_covariate.csv")
d$condition <- factor(d$condition); d$session <- factor(d$session); d$language <- factor(d$language)
options(contrasts=c("contr.sum","contr.poly"))
m <- lmer(trust ~ condition*session + language + (1|participant), data=d, REML=TRUE)
print(anova(m, type=3, ddf="Satterthwaite"), digits=10)
suppressMessages(library(emmeans))
e <- as.data.frame(emmeans(m, ~ condition*session, lmer.df="satterthwaite"))
print(head(e, 3), digits=10)
