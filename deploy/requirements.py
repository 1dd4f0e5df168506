"""Print the dependencies of swimm's core and the named optional groups, one a line, for `pip install -r`.

The Dockerfiles install these in a layer of their own before copying the source, so editing code
rebuilds only the small last layer and the big downloads (torch, MuJoCo) stay cached.

    python3 deploy/requirements.py sim > requirements.txt
"""

import sys
import tomllib

project = tomllib.load(open("pyproject.toml", "rb"))["project"]
groups = project.get("optional-dependencies", {})
unknown = [name for name in sys.argv[1:] if name not in groups]
if unknown:
    sys.exit(f"unknown optional-dependency groups {unknown}; pyproject.toml has {sorted(groups)}")
wanted = [*project["dependencies"], *(req for name in sys.argv[1:] for req in groups[name])]
print("\n".join(dict.fromkeys(wanted)))
