"""``python -m minimdm.aamdm train CONFIG [--out DIR]``: train an AAMDM motion model."""

from minimdm.aamdm.motion_train import main

if __name__ == "__main__":
    main()
