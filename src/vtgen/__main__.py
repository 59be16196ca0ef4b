from vtgen.cli import main
import sys
sys.exit(main())
