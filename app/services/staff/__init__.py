"""Staff accounts: creation and sign-in, their lifecycle, and the login throttle."""
