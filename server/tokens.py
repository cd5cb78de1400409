"""The form of the station's credentials, known to the code that makes them
(:mod:`server.link.robots`) and to the code that masks them in logs (:mod:`server.logs`)."""

# robot tokens start with it: it marks them as steelscan robot tokens (for secret scanners)
# and keeps them from starting with "-", which a command line would read as an option
TOKEN_PREFIX = "ssr_"
