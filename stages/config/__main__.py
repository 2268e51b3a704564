from .workflow import main

raise SystemExit(main())
