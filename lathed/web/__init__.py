"""lathed-web: the operator view, a separate process that reads the daemon
only through its control socket (the process commanding the machines keeps
no network listener)."""
