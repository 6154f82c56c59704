"""Analysis views: from the database to the analysis package and back as pages: the study dataset,
the overview and live dashboard, the analysis, mixed-model and power pages, registrations, and the
shared computation cache."""
