"""A copy of a SAC policy that records another CMVAE as its encoder, to fly a policy unchanged on a fine-tuned
encoder in a selection run (docs/encoder.md, "A low sun's shafts in perspective"). `swimm eval` refuses a policy
with an encoder other than the one it trained on; this copy says openly which encoder it now flies on.

    python docs/eval_report/selection/fans/rebind_encoder.py POLICY.zip ENCODER.pt OUT.zip
"""

import sys

from stable_baselines3 import SAC

from learner_service.identity import policy_identity, read_identity, stamp


def main(policy: str, encoder: str, out: str) -> None:
    task = read_identity(policy)["task"]
    model = SAC.load(policy, device="cpu")
    stamp(model, policy_identity(encoder, task["obs"], task["reward"], task["name"]))
    model.save(out)
    print(f"{out}: {policy} flying on {encoder}")


if __name__ == "__main__":
    main(*sys.argv[1:])
