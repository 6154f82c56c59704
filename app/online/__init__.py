"""Online studies: participants from a recruitment platform join by a public link and run the
study in their own browser, with no experimenter (issue 51, docs/online.md).

The lab's session runtime is used as it is: each online participant gets a virtual station of
their own, and the pages here act where an experimenter would (enrol, seat, start a session)."""
