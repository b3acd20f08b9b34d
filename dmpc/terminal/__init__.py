"""What a command shows on the terminal and how a process ends: consoles, error lines, exit codes."""
