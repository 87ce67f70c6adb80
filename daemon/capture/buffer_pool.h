#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <new>
#include <utility>
#include <vector>

namespace keyframed {

// A fixed number of reusable objects handed out as shared_ptr. When the last
// holder lets go, the deleter gives the object back to the pool instead of
// freeing it. The shared_ptr control blocks come from the pool's own free list
// too, so after warm-up acquire() and release make no heap allocation.
// Thread-safe; objects may outlive the pool (they are then simply deleted).
template <typename T>
class BufferPool {
 public:
  // `capacity` objects at most, made on demand by `make` (default: T{}).
  explicit BufferPool(std::size_t capacity, std::function<std::unique_ptr<T>()> make = {})
      : state_(std::make_shared<State>()) {
    state_->capacity = capacity;
    state_->make = make ? std::move(make) : [] { return std::make_unique<T>(); };
    state_->free.reserve(capacity);
    state_->blocks.reserve(capacity);
  }
  BufferPool(const BufferPool&) = delete;
  BufferPool& operator=(const BufferPool&) = delete;

  // An object no one else holds, or nullptr when all `capacity` are in use.
  [[nodiscard]] std::shared_ptr<T> acquire() {
    T* raw = nullptr;
    {
      std::lock_guard lock(state_->mutex);
      if (!state_->free.empty()) {
        raw = state_->free.back().release();
        state_->free.pop_back();
      } else if (state_->created < state_->capacity) {
        ++state_->created;
      } else {
        ++state_->exhausted;
        return nullptr;
      }
    }
    if (raw == nullptr) {
      try {
        raw = state_->make().release();
      } catch (...) {
        std::lock_guard lock(state_->mutex);
        --state_->created;  // the slot is free again for the next acquire()
        throw;
      }
    }
    return std::shared_ptr<T>(raw, Returner{state_}, BlockAllocator<T>{state_});
  }

  [[nodiscard]] std::size_t capacity() const { return state_->capacity; }
  // Objects made so far (<= capacity).
  [[nodiscard]] std::size_t created() const {
    std::lock_guard lock(state_->mutex);
    return state_->created;
  }
  // Objects sitting in the pool, ready for acquire().
  [[nodiscard]] std::size_t available() const {
    std::lock_guard lock(state_->mutex);
    return state_->free.size() + (state_->capacity - state_->created);
  }
  // acquire() calls that found the pool empty.
  [[nodiscard]] std::uint64_t exhaustedCount() const {
    std::lock_guard lock(state_->mutex);
    return state_->exhausted;
  }
  // Heap allocations made for shared_ptr control blocks (stays at most
  // `capacity` however many frames pass).
  [[nodiscard]] std::uint64_t controlBlockAllocations() const {
    std::lock_guard lock(state_->mutex);
    return state_->blockAllocations;
  }

 private:
  struct State {
    mutable std::mutex mutex;
    std::size_t capacity = 0;
    std::size_t created = 0;
    std::uint64_t exhausted = 0;
    std::uint64_t blockAllocations = 0;
    std::size_t blockSize = 0;
    std::function<std::unique_ptr<T>()> make;
    std::vector<std::unique_ptr<T>> free;
    std::vector<void*> blocks;  // free control-block memory, all of blockSize bytes

    ~State() {
      for (void* b : blocks) ::operator delete(b);
    }
  };

  struct Returner {
    std::weak_ptr<State> state;
    void operator()(T* p) const {
      std::unique_ptr<T> owned(p);
      if (auto s = state.lock()) {
        std::lock_guard lock(s->mutex);
        // Never grows: at most `capacity` objects exist.
        s->free.push_back(std::move(owned));
      }
    }
  };

  // Recycles the control block of each shared_ptr. It holds the state alive
  // (shared) because the control block is freed after the deleter ran.
  template <typename U>
  struct BlockAllocator {
    using value_type = U;
    std::shared_ptr<State> state;

    explicit BlockAllocator(std::shared_ptr<State> s) : state(std::move(s)) {}
    template <typename V>
    BlockAllocator(const BlockAllocator<V>& other) : state(other.state) {}

    U* allocate(std::size_t n) {
      const std::size_t bytes = n * sizeof(U);
      {
        std::lock_guard lock(state->mutex);
        if (bytes == state->blockSize && !state->blocks.empty()) {
          void* b = state->blocks.back();
          state->blocks.pop_back();
          return static_cast<U*>(b);
        }
        ++state->blockAllocations;
        if (state->blockSize == 0) state->blockSize = bytes;
      }
      return static_cast<U*>(::operator new(bytes));
    }
    void deallocate(U* p, std::size_t n) {
      const std::size_t bytes = n * sizeof(U);
      std::lock_guard lock(state->mutex);
      if (bytes == state->blockSize && state->blocks.size() < state->capacity) {
        state->blocks.push_back(p);  // capacity reserved: no allocation here
        return;
      }
      ::operator delete(p);
    }
    template <typename V>
    bool operator==(const BlockAllocator<V>& other) const {
      return state == other.state;
    }
  };

  std::shared_ptr<State> state_;
};

}  // namespace keyframed
