from magcomp.cli import main

raise SystemExit(main())
