"""`python -m mazebot` is the same as the `mazebot` command."""

from mazebot.cli import main

raise SystemExit(main())
