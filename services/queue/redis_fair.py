"""The Redis queue's fair share of workers per owner, and its per-key locks (Lua; used by
:mod:`services.queue.redis_queue`).

    ndrf:wait:<owner>     list of the owner's waiting job ids (marker ``w`` in ndrf:queued)
    ndrf:owners           sorted set of owners with waiting jobs, scored by the turn each was last
                          served at (0: never): the lowest is served next
    ndrf:served           hash owner -> the turn it was last served at (kept while it has no waiting
                          job, so an owner that comes back is not served ahead of its turn)
    ndrf:turn             the turn counter
    ndrf:wake             a short list pushed on every enqueue: idle workers block on it (BLPOP)
    ndrf:running:<owner>  set of the owner's jobs handed out by DISPATCH and not yet acked
    ndrf:job-owner        hash job -> owner, for those jobs (so that an ack finds the set)
    ndrf:lock:<name>      a per-key lock (SET NX PX with a token; released by compare-and-delete)

``enqueue`` puts a job in its owner's list; the stream ``ndrf:jobs`` then holds only jobs handed
to a worker: :data:`DISPATCH` first reads an entry of the stream nobody read yet (a job handed back
by ``requeue``, or one whose dispatcher died before reading it), otherwise moves the next job of
the least recently served owner that runs fewer than its cap of jobs (``NDRF_MAX_RUNNING_JOBS_PER_KEY``)
into the stream and reads it, in one step. Leases, renewals, acks and takeovers keep working on the
stream as before; an ack (or a hand-back) takes the job out of its owner's running set. A job handed
back is read again ahead of the others without counting against its owner's cap (it ran before).
"""

from __future__ import annotations

WAIT = "ndrf:wait:"
OWNERS = "ndrf:owners"
SERVED = "ndrf:served"
TURN = "ndrf:turn"
WAKE = "ndrf:wake"
RUNNING = "ndrf:running:"
LOCK = "ndrf:lock:{}"
WAKE_KEEP = 16

# KEYS stream, markers, beat, owners, served, wake   ARGV job, group, owner
ENQUEUE = """
local held = redis.call('HGET', KEYS[2], ARGV[1])
if held and not (string.sub(held, 1, 1) == '~' and
                 redis.call('EXISTS', 'ndrf:alive:' .. ARGV[1] .. ':' .. string.sub(held, 2)) == 0) then
  return false
end
if KEYS[3] ~= '' and redis.call('EXISTS', KEYS[3]) == 1 then return false end
redis.call('RPUSH', 'ndrf:wait:' .. ARGV[3], ARGV[1])
redis.call('HSET', KEYS[2], ARGV[1], 'w')
local turn = redis.call('HGET', KEYS[5], ARGV[3]) or '0'
redis.call('ZADD', KEYS[4], 'NX', turn, ARGV[3])
redis.call('RPUSH', KEYS[6], '1')
redis.call('LTRIM', KEYS[6], -16, -1)
return 'w'
"""

# KEYS stream, markers, owners, served, turn   ARGV group, consumer, running cap per owner (0: none)
DISPATCH = """
redis.pcall('XGROUP', 'CREATE', KEYS[1], ARGV[1], '0', 'MKSTREAM')
local function read()
  return redis.call('XREADGROUP', 'GROUP', ARGV[1], ARGV[2], 'COUNT', 1, 'STREAMS', KEYS[1], '>')
end
local got = read()
if got then return got end
local cap = tonumber(ARGV[3])
local function pick()
  for _, o in ipairs(redis.call('ZRANGE', KEYS[3], 0, -1)) do
    if cap == 0 or redis.call('SCARD', 'ndrf:running:' .. o) < cap then return o end
  end
  return nil
end
for _ = 1, 256 do
  local owner = pick()
  if not owner then return false end
  local list = 'ndrf:wait:' .. owner
  local job = redis.call('LPOP', list)
  if not job then
    redis.call('ZREM', KEYS[3], owner)
  elseif redis.call('HGET', KEYS[2], job) ~= 'w' then
    -- no longer waiting (canceled while queued): dropped without spending the owner's turn
    if redis.call('LLEN', list) == 0 then redis.call('ZREM', KEYS[3], owner) end
  else
    local turn = redis.call('INCR', KEYS[5])
    redis.call('HSET', KEYS[4], owner, turn)
    if redis.call('LLEN', list) == 0 then redis.call('ZREM', KEYS[3], owner)
    else redis.call('ZADD', KEYS[3], turn, owner) end
    local id = redis.call('XADD', KEYS[1], '*', 'job', job)
    redis.call('HSET', KEYS[2], job, id)
    redis.call('SADD', 'ndrf:running:' .. owner, job)
    redis.call('HSET', 'ndrf:job-owner', job, owner)
    return read()
  end
end
return false
"""

# KEYS markers, owners   ARGV job, owner: a job canceled while it waits leaves its owner's list
WITHDRAW = """
if redis.call('HGET', KEYS[1], ARGV[1]) ~= 'w' then return 0 end
local list = 'ndrf:wait:' .. ARGV[2]
local removed = redis.call('LREM', list, 0, ARGV[1])
redis.call('HDEL', KEYS[1], ARGV[1])
if redis.call('LLEN', list) == 0 then redis.call('ZREM', KEYS[2], ARGV[2]) end
return removed
"""

# Lua run by the queue's release script when a delivery is acked or handed back (ARGV[4]: the job)
RELEASE_RUNNING = """
local runner = redis.call('HGET', 'ndrf:job-owner', ARGV[4])
if runner then
  redis.call('SREM', 'ndrf:running:' .. runner, ARGV[4])
  redis.call('HDEL', 'ndrf:job-owner', ARGV[4])
  redis.call('RPUSH', 'ndrf:wake', '1')
  redis.call('LTRIM', 'ndrf:wake', -16, -1)
end
"""

# KEYS owners   the number of jobs waiting in every owner's list
WAITING = """
local n = 0
for _, owner in ipairs(redis.call('ZRANGE', KEYS[1], 0, -1)) do
  n = n + redis.call('LLEN', 'ndrf:wait:' .. owner)
end
return n
"""

# KEYS lock   ARGV token
UNLOCK = """
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end
return 0
"""
