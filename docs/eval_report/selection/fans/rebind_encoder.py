"""A copy of a policy zip whose recorded encoder is another CMVAE, to fly a policy unchanged on a fine-tuned
encoder in a selection run (docs/encoder.md, "A low sun's shafts in perspective"). `swimm eval` refuses a policy
with an encoder other than the one it trained on; this copy says openly which encoder it now flies on.

    python docs/eval_report/selection/fans/rebind_encoder.py POLICY.zip ENCODER.pt OUT.zip
"""

import json
import sys
import zipfile

from learner_service.identity import IDENTITY_KEY
from services.results import file_sha256


def main(policy: str, encoder: str, out: str) -> None:
    with zipfile.ZipFile(policy) as source, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as copy:
        for name in source.namelist():
            content = source.read(name)
            if name == "data":
                data = json.loads(content)
                data[IDENTITY_KEY]["encoder"] = {"path": encoder, "sha256": file_sha256(encoder)}
                content = json.dumps(data, indent=4).encode()
            copy.writestr(name, content)
    print(f"{out}: {policy} flying on {encoder}")


if __name__ == "__main__":
    main(*sys.argv[1:])
