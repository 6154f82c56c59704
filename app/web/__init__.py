"""Server-rendered pages (Jinja2 + htmx) for experimenters, analysts and admins."""
