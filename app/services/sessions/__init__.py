"""Sessions and the runtime: stations and their devices, sessions, runs, prompts and exactly-once
answers, the learners behind them (and their populations), the robot's replies, the room's live
state and recorded answers, and the integrity check that replays them."""
