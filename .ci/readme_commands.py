"""Print the README's set-up commands, one per line, exactly as written.

They are the shell lines of the ```bash blocks under the heading "Two commands on a fresh
machine": CI runs these very lines, so the README cannot drift from what is tested.
"""

import re
import sys
from pathlib import Path

text = Path(__file__).resolve().parent.parent.joinpath("README.md").read_text()
section = re.search(r"^## Two commands on a fresh machine\n(.*?)(?=^## )", text, re.S | re.M)
if section is None:
    sys.exit("README.md: no section 'Two commands on a fresh machine'")
commands = [line.strip() for block in re.findall(r"```bash\n(.*?)```", section.group(1), re.S)
            for line in block.splitlines() if line.strip() and not line.strip().startswith("#")]
if len(commands) != 2:
    sys.exit(f"README.md: expected two commands, found {len(commands)}: {commands}")
print("\n".join(commands))
